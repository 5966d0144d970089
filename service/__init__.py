"""The onboard service: `treetraits run` wires the live sensors to the pipeline.

One process, one receive thread per source feeding a bounded queue (`workers`), the
processing loop on the main thread (`runtime`), the run's outputs shared with `treetraits
replay` (`outputs`), per-sensor health (`health`) and the systemd protocol (`notify`).
The configuration is `config`; docs/service.md is the reference.
"""

from pathlib import Path

# Where `make install` puts the config. Here, not in config.py, so that the command line's
# help reads it without loading the config's schema (and through it, the pipeline).
DEFAULT_CONFIG_PATH = Path("/etc/treetraits/config.toml")
