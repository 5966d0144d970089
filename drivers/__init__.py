"""Sensor drivers: wire formats, live and replay sources, no algorithms.

The sensors' factory settings that the command line's help shows live here, with no
imports, so that building its parser (`treetraits --help`) loads no driver.
"""

DATA_PORT = 2368  # VLP-16 data packets (UDP)
TELEMETRY_PORT = 8308  # VLP-16 position packets (UDP)
DEFAULT_BAUD = 9600  # most GNSS receivers' factory setting (u-blox ZED-F9P UART1: 38400)
