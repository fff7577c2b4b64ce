"""pyinfra facts and operations roslab needs beyond pyinfra's own, one module per tool.

The convention: a tool's facts and its operations sit together in one module (roslab.ops.apt
holds AptProblem beside apt_lists_updated), where pyinfra keeps them in a pair of modules of the
same name (pyinfra/facts/apt.py beside pyinfra/operations/apt.py). A module may use another's
facts and operations (apt reads files.FileAge); none imports a deploy, and none imports
another in return (tests/unit/test_layout.py holds the modules free of import cycles).

    apt             Ubuntu apt sources, package lists, dpkg's interrupted installs, packages
    boot_config     a Pi's config.txt and cmdline.txt, the host's "reboot needed" record
    class_lock      the class lock on a host: installed and offered versions, apt pins, moves
    files           managed blocks, files moved aside, a file's age, files renamed into place
    locale          a generated locale
    memory          the host's RAM, a swap file
    profile_record  what roslab wrote for a host's robot profile, and what goes when it changes
    rosdep          rosdep's sources list and a user's cache
    systemd         a finished boot, masked units, a service installed but not running
    udev            udev re-reads its rules
    users           the login user's groups, running as a user

Tools with a folder of their own keep their facts and operations there, one module each:
roslab.ros.workspace (colcon workspace), roslab.python_env.venv, roslab.ssh.sshd,
roslab.network.operation, roslab.sources.underlay.

Each operation is named for the end state, reads facts, and either yields the commands that
reach that state or says with ``host.noop`` why nothing needs doing. Facts are read again when
an operation executes, so an operation that follows another one sees its effect. Each fact is
one remote command; none of them changes the host.
"""
