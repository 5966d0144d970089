"""Robot pose in UTM from wheel odometry, GNSS fixes and headings (no ROS).

`Localizer` is the entry point; the modules beside it are the pure pieces it is made of.
"""

from treetraits.pipeline.localization.config import LocalizationConfig, WheelGeometry
from treetraits.pipeline.localization.localizer import FixVerdict, Localizer

__all__ = ["FixVerdict", "LocalizationConfig", "Localizer", "WheelGeometry"]
