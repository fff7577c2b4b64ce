"""SSH: the hosts' identity (keys, known_hosts), sshd's settings, sudo, and paramiko kept quiet."""
