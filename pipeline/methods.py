"""The names `pipeline.method` and `traits.method` take. A module of their own, with no
imports: the command line's parsers list them as choices without loading the config's
schema (pipeline/config.py, which `treetraits --help` would otherwise pay for)."""

# pipeline.method: rph is the baseline as shipped; rph-vlp16 RPH retuned for single VLP-16 scans.
METHODS = ("paper", "rph", "rph-vlp16")
TRAIT_METHODS = ("paper", "robust")
