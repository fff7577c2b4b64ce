"""The sandbox classroom: test hosts on this machine that look to the deploys like Pis.

Hosts are systemd-booted containers (systemd-nspawn), each in its own network
namespace, reached over SSH as a sudo user. A local "upstream" stands in for
the internet. See docs/sandbox.md for what is emulated, what is a stand-in,
and what is real.
"""
