"""Where the checkout and the test fixtures are, from this file's own place (the tests sit
at different depths)."""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
FIXTURES = REPO / "tests" / "fixtures"
# The real CitrusFarm calibration (Survey3N + VLP-16 on a Jackal).
CITRUSFARM = FIXTURES / "citrusfarm_calib" / "citrusfarm_calibration_v1.json"
