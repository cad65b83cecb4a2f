"""Instance masks as arrays: boxes, Dice, overlap between classes and edge refinement."""
