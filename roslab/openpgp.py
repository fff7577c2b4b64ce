"""OpenPGP public keys as apt reads them: the binary key (apt's Signed-By reads either form, the
keyring files roslab writes are binary) and the fingerprint of a key's primary key, which is
how an archive publishes its key (the ROS snapshot repository's: `SNAPSHOTS_FINGERPRINT`).

Only the first packet of a key is read, which RFC 4880 (section 11.1) and RFC 9580 (10.1) make
the primary public key: its fingerprint is the SHA-1 of `0x99`, a two-octet length and the
packet's body for a version 4 key (RFC 4880 12.2), the SHA-256 of `0x9B`, a four-octet length
and the body for a version 6 key (RFC 9580 5.5.4).
"""

from __future__ import annotations

import base64
import binascii
import hashlib

ARMOR_BEGIN = "-----BEGIN PGP PUBLIC KEY BLOCK-----"
ARMOR_END = "-----END PGP PUBLIC KEY BLOCK-----"
PUBLIC_KEY_TAG = 6

# The key of snapshots.ros.org, as the ROS 2 documentation publishes it ("Installing from the
# snapshot repository": 4B63 CF8F DE49 746E 98FA 01DD AD19 BAB3 CBF1 25EA); not the key of
# packages.ros.org, which ros2-apt-source installs.
SNAPSHOTS_FINGERPRINT = "4B63CF8FDE49746E98FA01DDAD19BAB3CBF125EA"


class UnreadableKey(ValueError):
    """The bytes are not an OpenPGP public key roslab can read (the message says why)."""


def dearmored(key: bytes) -> bytes:
    """An OpenPGP key as binary, un-armoring it if needed (a binary key is returned as is)."""
    text = key.decode("ascii", errors="replace")
    if ARMOR_BEGIN not in text:
        return key
    body = text.split(ARMOR_BEGIN, 1)[1].split(ARMOR_END, 1)[0]
    lines = [line.strip() for line in body.strip().splitlines()]
    if "" in lines:  # armor headers ("Version: ...") end at the first blank line
        lines = lines[lines.index("") + 1:]
    # The "=XXXX" line is the armor's checksum, not key data.
    data = "".join(line for line in lines if line and not line.startswith("="))
    try:
        return base64.b64decode(data, validate=True)
    except binascii.Error as error:
        raise UnreadableKey(f"its armored block is not base64 ({error})") from error


def _first_packet(data: bytes) -> tuple[int, bytes]:
    """(tag, body) of the first packet (RFC 4880 4.2: old and new packet headers)."""
    if not data or not data[0] & 0x80:
        raise UnreadableKey("it does not start with an OpenPGP packet")
    first = data[0]
    if first & 0x40:  # new format: the tag in 6 bits, then a one-, two- or five-octet length
        tag, octet = first & 0x3F, data[1:2]
        if not octet:
            raise UnreadableKey("its first packet is cut short")
        if octet[0] < 192:
            length, start = octet[0], 2
        elif octet[0] < 224:
            if len(data) < 3:
                raise UnreadableKey("its first packet is cut short")
            length, start = ((octet[0] - 192) << 8) + data[2] + 192, 3
        elif octet[0] == 255:
            length, start = int.from_bytes(data[2:6], "big"), 6
        else:
            raise UnreadableKey("its first packet has a partial length, which a key packet never has")
    else:  # old format: the tag in 4 bits, the length's size in 2
        tag, kind = (first >> 2) & 0x0F, first & 0x03
        if kind == 3:
            raise UnreadableKey("its first packet has an indeterminate length")
        size = 1 << kind
        length, start = int.from_bytes(data[1:1 + size], "big"), 1 + size
    body = data[start:start + length]
    if len(body) != length:
        raise UnreadableKey("its first packet is cut short")
    return tag, body


def fingerprint(key: bytes) -> str:
    """The fingerprint of `key`'s primary key (armored or binary), upper-case hex without spaces."""
    tag, body = _first_packet(dearmored(key))
    if tag != PUBLIC_KEY_TAG:
        raise UnreadableKey(f"its first packet is not a public key (tag {tag}, not {PUBLIC_KEY_TAG})")
    version = body[:1]
    if version == b"\x04":
        return hashlib.sha1(b"\x99" + len(body).to_bytes(2, "big") + body, usedforsecurity=False).hexdigest().upper()
    if version == b"\x06":
        return hashlib.sha256(b"\x9b" + len(body).to_bytes(4, "big") + body).hexdigest().upper()
    raise UnreadableKey(f"its primary key is version {body[0] if body else '?'}, not 4 or 6")


def spaced(fingerprint_hex: str) -> str:
    """A fingerprint as people compare it: groups of four, two spaces in the middle."""
    groups = [fingerprint_hex[i:i + 4] for i in range(0, len(fingerprint_hex), 4)]
    half = len(groups) // 2
    return " ".join(groups[:half]) + "  " + " ".join(groups[half:])
