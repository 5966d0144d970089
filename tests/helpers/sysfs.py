"""A sysfs tree laid out as Linux lays it out for UVC cameras, and their /dev nodes."""

from __future__ import annotations


def make_sysfs(root, cameras):
    """cameras: (first video number, name, vid, pid, usb port name) -> two nodes each."""
    sysfs, dev = root / "sys", root / "dev"
    dev.mkdir(parents=True)
    for number, name, vid, pid, port in cameras:
        bus = port.split("-")[0]
        usb_dir = sysfs / "devices" / "pci0000:00" / "0000:00:14.0" / f"usb{bus}" / port
        interface = usb_dir / f"{port}:1.0"
        interface.mkdir(parents=True, exist_ok=True)
        (usb_dir / "idVendor").write_text(f"{vid}\n")
        (usb_dir / "idProduct").write_text(f"{pid}\n")
        (usb_dir / "product").write_text(f"{name}\n")
        listed = sysfs / "bus" / "usb" / "devices" / port
        listed.parent.mkdir(parents=True, exist_ok=True)
        listed.symlink_to(usb_dir)
        for offset in (0, 1):
            node = sysfs / "class" / "video4linux" / f"video{number + offset}"
            node.mkdir(parents=True)
            (node / "name").write_text(f"{name}\n")
            (node / "index").write_text(f"{offset}\n")
            (node / "device").symlink_to(interface)
    return sysfs, dev
