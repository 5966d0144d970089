"""The orchard digital twin (docs/sim_replay.md)."""

# The robot paths `treetraits sim --path` offers (sim/paths.py drives them). Here, with no
# imports, so that building the command line's parser loads none of the twin.
PATHS = ("straight", "s", "n")
