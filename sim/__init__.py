"""The orchard digital twin (docs/sim_replay.md)."""

# The robot paths `treetraits sim --path` offers (sim/paths.py drives them). Here, with no
# imports, so that building the command line's parser loads none of the twin.
PATHS = ("straight", "s", "n")
# The foliage models `--foliage` offers (sim/foliage.py grows them, in this order).
FOLIAGE_MODELS = ("scattered", "dense", "broadleaf", "clumped", "sparse")
