"""STAND-INS of a Raspberry Pi's boot partition, for sandbox hosts whose roster `board` is a Pi.

A sandbox host is a container: it has no SD card and no FAT partition. A host whose board is a
Raspberry Pi (roslab.boards) gets, where Ubuntu mounts that partition (/boot/firmware), the
two files roslab's deploys read and change there, as Ubuntu's preinstalled server image for the
Pi has them on first boot:

- `config.txt`: the firmware's configuration; the stand-in's first line names it a stand-in
  (config.txt takes `#` comments), the rest is Ubuntu's file byte for byte;
- `cmdline.txt`: the kernel's command line, one line, exactly Ubuntu's (it takes no comment);
- `README.roslab-sandbox`: says what the two files are.

No firmware reads them here: a change to them is real to the deploy (its managed block, its
backup, its "reboot needed" record) and nothing else. The files are the same for every Pi
board of a release (the firmware picks its `[pi4]`, `[pi3+]`, `[cm4]` sections itself).

Source of the content: Ubuntu's pi-gadget (github.com/canonical/pi-gadget, branch `classic`,
commit c042c9a9504521855f266302cce4953a1dfddf5d; its Makefile copies
configs/<series>-arm64-server/* into the image's boot assets): configs/jammy-arm64-server/ for
22.04, configs/noble-arm64-server/ for 24.04. 26.04 has no server configs there yet: a 26.04
host gets no boot partition stand-in (a profile's boot config is then skipped there, as on a PC).
"""

from __future__ import annotations

from roslab import boards

BOOT_PARTITION = "/boot/firmware"  # where Ubuntu for Pi mounts the boot partition
PI_BOARDS = boards.PI_NAMES  # roslab.settings `board` values that are a Raspberry Pi
SOURCE = ("github.com/canonical/pi-gadget, branch classic, commit c042c9a9504521855f266302cce4953a1dfddf5d, "
          "configs/{series}-arm64-server/")
STANDIN_LINE = ("# roslab sandbox STAND-IN of Ubuntu {release}'s /boot/firmware/config.txt for a Raspberry Pi "
                "(from {source}): no firmware reads it here.\n")

CONFIG_TXT = {
    "22.04": (
    '[all]\n'
    'kernel=vmlinuz\n'
    'cmdline=cmdline.txt\n'
    'initramfs initrd.img followkernel\n'
    '\n'
    '[pi4]\n'
    'max_framebuffers=2\n'
    'arm_boost=1\n'
    '\n'
    '[all]\n'
    '# Enable the audio output, I2C and SPI interfaces on the GPIO header. As these\n'
    '# parameters related to the base device-tree they must appear *before* any\n'
    '# other dtoverlay= specification\n'
    'dtparam=audio=on\n'
    'dtparam=i2c_arm=on\n'
    'dtparam=spi=on\n'
    '\n'
    '# Comment out the following line if the edges of the desktop appear outside\n'
    '# the edges of your display\n'
    'disable_overscan=1\n'
    '\n'
    '# If you have issues with audio, you may try uncommenting the following line\n'
    "# which forces the HDMI output into HDMI mode instead of DVI (which doesn't\n"
    '# support audio output)\n'
    '#hdmi_drive=2\n'
    '\n'
    '# Enable the serial pins\n'
    'enable_uart=1\n'
    '\n'
    '# Autoload overlays for any recognized cameras or displays that are attached\n'
    '# to the CSI/DSI ports. Please note this is for libcamera support, *not* for\n'
    '# the legacy camera stack\n'
    'camera_auto_detect=1\n'
    'display_auto_detect=1\n'
    '\n'
    '# Config settings specific to arm64\n'
    'arm_64bit=1\n'
    'dtoverlay=dwc2\n'
    '\n'
    '[cm4]\n'
    '# Enable the USB2 outputs on the IO board (assuming your CM4 is plugged into\n'
    '# such a board)\n'
    'dtoverlay=dwc2,dr_mode=host\n'
    '\n'
    '[all]\n'
),
    "24.04": (
    '[all]\n'
    'arm_64bit=1\n'
    'kernel=vmlinuz\n'
    'cmdline=cmdline.txt\n'
    'initramfs initrd.img followkernel\n'
    '\n'
    '# Enable the audio output, I2C and SPI interfaces on the GPIO header. As these\n'
    '# parameters related to the base device-tree they must appear *before* any\n'
    '# other dtoverlay= specification\n'
    'dtparam=audio=on\n'
    'dtparam=i2c_arm=on\n'
    'dtparam=spi=on\n'
    '\n'
    '# Comment out the following line if the edges of the desktop appear outside\n'
    '# the edges of your display\n'
    'disable_overscan=1\n'
    '\n'
    '# If you have issues with audio, you may try uncommenting the following line\n'
    "# which forces the HDMI output into HDMI mode instead of DVI (which doesn't\n"
    '# support audio output)\n'
    '#hdmi_drive=2\n'
    '\n'
    '# Enable the KMS ("full" KMS) graphics overlay, leaving GPU memory as the\n'
    '# default (the kernel is in control of graphics memory with full KMS)\n'
    'dtoverlay=vc4-kms-v3d\n'
    'disable_fw_kms_setup=1\n'
    '\n'
    '# Enable the serial pins\n'
    'enable_uart=1\n'
    '\n'
    '# Autoload overlays for any recognized cameras or displays that are attached\n'
    '# to the CSI/DSI ports. Please note this is for libcamera support, *not* for\n'
    '# the legacy camera stack\n'
    'camera_auto_detect=1\n'
    'display_auto_detect=1\n'
    '\n'
    '# Config settings specific to arm64\n'
    'dtoverlay=dwc2\n'
    '\n'
    '[pi4]\n'
    'max_framebuffers=2\n'
    'arm_boost=1\n'
    '\n'
    '[pi3+]\n'
    '# Use a smaller contiguous memory area, specifically on the 3A+ to avoid an\n'
    "# OOM oops on boot. The 3B+ is also affected by this section, but it shouldn't\n"
    '# cause any issues on that board\n'
    'dtoverlay=vc4-kms-v3d,cma-128\n'
    '\n'
    '[pi02]\n'
    '# The Zero 2W is another 512MB board which is occasionally affected by the same\n'
    '# OOM oops on boot.\n'
    'dtoverlay=vc4-kms-v3d,cma-128\n'
    '\n'
    '[cm4]\n'
    '# Enable the USB2 outputs on the IO board (assuming your CM4 is plugged into\n'
    '# such a board)\n'
    'dtoverlay=dwc2,dr_mode=host\n'
    '\n'
    '[all]\n'
),
}
CMDLINE_TXT = {
    "22.04": 'console=serial0,115200 dwc_otg.lpm_enable=0 console=tty1 root=LABEL=writable rootfstype=ext4 rootwait fixrtc quiet splash\n',
    "24.04": 'console=serial0,115200 multipath=off dwc_otg.lpm_enable=0 console=tty1 root=LABEL=writable rootfstype=ext4 rootwait fixrtc\n',
}
SERIES = {"22.04": "jammy", "24.04": "noble"}

README = (
    "roslab sandbox: this host's board is a Raspberry Pi ({board}); a container has no SD card, so\n"
    "this folder is a STAND-IN of its boot partition: config.txt and cmdline.txt are Ubuntu\n"
    "{release}'s, as its preinstalled server image for the Pi has them ({source}).\n"
    "No firmware reads them here; roslab's deploys change them as on a Pi (roslab/sandbox/pi_boot.py).\n"
)


def is_pi(board: str | None) -> bool:
    """Whether a roster `board` is a Raspberry Pi."""
    return board in PI_BOARDS


def boot_files(board: str | None, release: str) -> dict[str, tuple[str, int]]:
    """The boot partition stand-in of a host (path -> (content, mode)): empty for a board that is
    not a Pi (a PC, not said) and for a release pi-gadget has no server configs of."""
    if not is_pi(board) or release not in CONFIG_TXT:
        return {}
    source = SOURCE.format(series=SERIES[release])
    return {
        f"{BOOT_PARTITION}/config.txt": (STANDIN_LINE.format(release=release, source=source) + CONFIG_TXT[release],
                                         0o644),
        f"{BOOT_PARTITION}/cmdline.txt": (CMDLINE_TXT[release], 0o644),
        f"{BOOT_PARTITION}/README.roslab-sandbox": (README.format(board=board, release=release, source=source),
                                                    0o644),
    }
