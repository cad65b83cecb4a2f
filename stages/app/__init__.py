"""The app: the config schema, the graph of stage nodes (pipeline), preflight, the summary and report of a run,
and the commands (`python -m stages.app.<command>`: export, predict, dataset_card). The only code that imports
the stages' specs."""
