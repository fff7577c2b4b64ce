"""Test deploy for tests/e2e/test_ssh_hardening_e2e.py: the two SSH steps of deploy.py, in its order.

The teacher's keys are authorised first (ssh_identity), then sshd is hardened (ssh_hardening);
the ROS steps are left out to keep the test short.
"""

from deploy.ssh_hardening import ssh_hardening
from deploy.ssh_identity import ssh_identity

ssh_identity()
ssh_hardening()
