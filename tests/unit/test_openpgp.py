"""OpenPGP keys (roslab/openpgp.py): un-armoring, and fingerprints as gpg reports them
(the test keys of fixtures/openpgp_keys.py)."""

from __future__ import annotations

import pytest
from fixtures.openpgp_keys import ED25519_ARMORED, ED25519_FINGERPRINT, RSA_BINARY, RSA_FINGERPRINT

from roslab import openpgp


def test_the_fingerprints_are_gpgs_for_an_armored_and_a_binary_key():
    assert openpgp.fingerprint(ED25519_ARMORED.encode()) == ED25519_FINGERPRINT
    assert openpgp.fingerprint(RSA_BINARY) == RSA_FINGERPRINT


def test_old_and_new_packet_headers_give_the_same_fingerprint():
    binary = openpgp.dearmored(ED25519_ARMORED.encode())
    assert binary[0] == 0x98  # old format, one-octet length (what gpg writes)
    length = binary[1]
    new_format = bytes([0xC6, length]) + binary[2:]
    assert openpgp.fingerprint(new_format) == ED25519_FINGERPRINT
    five_octet = bytes([0xC6, 0xFF]) + length.to_bytes(4, "big") + binary[2:]
    assert openpgp.fingerprint(five_octet) == ED25519_FINGERPRINT
    assert RSA_BINARY[0] == 0x99  # old format, two-octet length


def test_dearmoring_leaves_a_binary_key_alone():
    assert openpgp.dearmored(RSA_BINARY) == RSA_BINARY
    assert openpgp.dearmored(ED25519_ARMORED.encode())[:1] == b"\x98"


@pytest.mark.parametrize("data, problem", [
    (b"", "does not start with an OpenPGP packet"),
    (b"not a key at all", "does not start with an OpenPGP packet"),
    (bytes([0x94, 0x02, 0x04, 0x00]), "not a public key (tag 5"),  # a secret key packet
    (bytes([0x98, 0x10, 0x04]), "cut short"),
    (bytes([0x98, 0x02, 0x03, 0x00]), "version 3, not 4 or 6"),
    (b"-----BEGIN PGP PUBLIC KEY BLOCK-----\n\n%%%\n-----END PGP PUBLIC KEY BLOCK-----\n", "not base64"),
])
def test_what_is_not_a_readable_public_key_is_named(data, problem):
    with pytest.raises(openpgp.UnreadableKey, match=problem.replace("(", r"\(")):
        openpgp.fingerprint(data)


def test_a_fingerprint_is_shown_as_the_ros_documentation_prints_it():
    assert openpgp.spaced(openpgp.SNAPSHOTS_FINGERPRINT) == "4B63 CF8F DE49 746E 98FA  01DD AD19 BAB3 CBF1 25EA"
