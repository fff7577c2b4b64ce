"""First-boot seeds: the NoCloud files that boot a freshly flashed Pi into the roster.

    roslab seed [ROSTER] --out DIR                           DIR/<host>/{user-data,network-config,meta-data}
    roslab seed [ROSTER] --boot-partition PATH --limit NAME  a mounted Ubuntu Pi system-boot partition
    roslab seed [ROSTER] --image FILE --limit NAME           a raw Ubuntu Pi image, written with mtools

    documents.py   the three files of one host, built as data and dumped as YAML
    tools.py       cloud-init's and netplan's own checks, unpacked from Debian's packages
    targets.py     writing them: a directory, a boot partition, an image's FAT partition

Everything is checked before anything is written: the roster (`load_roster`), what a
seed needs beyond it (an SSH key for the lab user), cloud-init's schema check of every
user-data and netplan's parser on every network-config. A second run with the same
roster writes nothing (the files are byte-identical; each host's key is generated once,
`roslab.ssh.identity`).
"""

from roslab.seed.documents import SEED_FILES, SeedError, SeedFile, host_seed

__all__ = ["SEED_FILES", "SeedError", "SeedFile", "host_seed"]
