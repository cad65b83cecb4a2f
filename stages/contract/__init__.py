"""The contract between a stage and the engine: StageError and EmptyInput (errors), the declaration of a
stage's inputs (inputs, fan_in) and enumerated settings (choices). Imports nothing else of the project."""
