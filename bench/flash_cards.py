"""Time `roslab flash` writing and verifying N loop-device cards at once against `dd` writing
the same image to them one after the other (no verification, no seed) on this machine.

    sudo .venv/bin/python bench/flash_cards.py [--cards 3] [--image-mb 512]

The image is the tests' stand-in Pi image (tests/pi_image.py) grown to --image-mb with its
writable partition. Loop devices over files in a temporary folder stand in for the cards.
Writes bench/results/flash_cards.md.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(REPO), str(REPO / "tests")]
import pi_image  # noqa: E402

from roslab.cli.main import main as roslab  # noqa: E402

TEACHER = "ssh-ed25519 AAAAC3NzaC1lZDI1NTE5AAAAIFlMtlfltx2Ordc++JZrFF/P0U8EAhdPijdaM3K81dM9 teacher"


def roster(folder: Path, count: int) -> Path:
    hosts = "".join(f"      pi{index}: {{role: {'main' if index == 0 else 'robot'}, address: 192.168.50.{11 + index}, "
                    f"network_address: 192.168.50.{11 + index}}}\n" for index in range(count))
    path = folder / "classroom.yaml"
    path.write_text(textwrap.dedent(f"""\
        classroom:
          teacher_ssh_keys: ["{TEACHER}"]
          ubuntu_release: "24.04"
          network_prefix: 24
          network_gateway: 192.168.50.1
          network_nameservers: [192.168.50.1]
        teams:
          team1:
            hosts:
        """) + hosts)
    return path


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--cards", type=int, default=3)
    parser.add_argument("--image-mb", type=int, default=512)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="roslab-bench-flash-") as folder:
        folder = Path(folder)
        image = pi_image.write(folder / "pi.img", root_mib=args.image_mb - 17)
        devices = []
        try:
            for index in range(args.cards):
                backing = folder / f"card{index}.bin"
                with open(backing, "wb") as card:
                    card.truncate((args.image_mb + 64) << 20)
                devices.append(subprocess.run(["losetup", "--find", "--show", str(backing)], check=True,
                                              capture_output=True, text=True).stdout.strip())
            started = time.monotonic()
            for device in devices:
                subprocess.run(["dd", f"if={image}", f"of={device}", "bs=4M", "conv=fsync"], check=True,
                               capture_output=True)
            dd_seconds = time.monotonic() - started
            started = time.monotonic()
            code = roslab(["flash", str(roster(folder, args.cards)), "--image", str(image), "-y", "--force",
                           *(word for device in devices for word in ("--device", device))])
            flash_seconds = time.monotonic() - started
        finally:
            for device in devices:
                subprocess.run(["losetup", "--detach", device], capture_output=True)
    line = (f"| {args.cards} | {args.image_mb} MB | {dd_seconds:.1f} s | {flash_seconds:.1f} s "
            f"| {'ok' if code == 0 else f'exit {code}'} |")
    out = REPO / "bench/results/flash_cards.md"
    if not out.exists():
        out.write_text("# roslab flash against dd (bench/flash_cards.py)\n\n"
                       "dd: the image written to each card in turn (no seed, no verification). roslab flash: all "
                       "cards at once, each read back and compared, seeded, the seed read back, marked done.\n"
                       "Loop devices over files stand in for cards (the page cache and one disk behind them: "
                       "real card readers are each their own bottleneck, where writing at once gains most).\n\n"
                       "| cards | image | dd, one by one | roslab flash, verified | result |\n|---|---|---|---|---|\n")
    with open(out, "a") as results:
        results.write(line + "\n")
    print(line)
    return code


if __name__ == "__main__":
    sys.exit(main())
