"""The packet encoder (used by the digital twin) against real packets: byte-exact."""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers.captures import VLP16_DIR
from treetraits.drivers.velodyne.encode import encode_packets
from treetraits.drivers.velodyne.packet import view_packets
from treetraits.drivers.velodyne.sources import open_source


@pytest.mark.parametrize(
    "name", ["einride_vlp16_strongest_1000pkts.bin", "nebula_vlp16_dual_10hz.pcap"]
)
def test_real_packets_re_encode_byte_for_byte(name):
    source = open_source(VLP16_DIR / name)
    payloads = [p.payload for p in source if p.is_data]
    source.close()
    original = b"".join(payloads)
    packets = view_packets(original)
    blocks = packets["blocks"]
    encoded = encode_packets(
        blocks["azimuth"],
        blocks["records"]["distance"],
        blocks["records"]["reflectivity"],
        packets["toh"],
        return_mode=int(packets["return_mode"][0]),
        product=int(packets["product"][0]),
    )
    assert encoded == original


def test_bad_shapes_and_values_are_refused():
    azimuth = np.zeros((2, 12), dtype=np.uint16)
    grid = np.zeros((2, 12, 32), dtype=np.uint16)
    with pytest.raises(ValueError, match="azimuth must be"):
        encode_packets(azimuth[:, :11], grid, grid, np.zeros(2))
    with pytest.raises(ValueError, match=r"0\.\.35999"):
        encode_packets(azimuth + 36000, grid, grid, np.zeros(2))
    with pytest.raises(ValueError, match="return mode"):
        encode_packets(azimuth, grid, grid, np.zeros(2), return_mode=0x40)
