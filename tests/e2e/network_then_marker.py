"""Test deploy for tests/e2e/test_network_e2e.py: the network deploy, then one more step.

The step after the network deploy records the address its SSH connection reached
($SSH_CONNECTION's third field), which shows where the rest of a deploy runs.
"""

from pyinfra.operations import server

from deploy.network import network

network()
server.shell(
    name="Record the address the deploy reaches the host at after the network deploy",
    commands=['echo "$SSH_CONNECTION" > /tmp/roslab-e2e-reached-at'],
    _sudo=False,
)
