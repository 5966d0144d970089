"""treetraits: an onboard orchard tree mapper (VLP-16 + Survey3N + GNSS + wheels, no ROS).

This package holds what every part shares: the version, the exception tree and the
command line. Sensor drivers live in `drivers/`, algorithms in `pipeline/`.
"""

__version__ = "0.1.0"
