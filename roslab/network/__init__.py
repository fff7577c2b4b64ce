"""The network deploy's code: each host at its fixed address, never locked out on the way.

Used by deploy/network.py (and by the roster loader, before any host is touched):

- `settings`: parse and check one host's network settings (`network_settings`,
  `NetworkSettingError` naming the roster field), and the classroom-wide check the
  roster loader runs (`validate_roster`: reports through `report.error`, never raises);
- `render`: which renderer and file format a host gets (`choose_layout`), the
  files' contents from the templates, each value escaped for its format, and the
  masking of WiFi passwords in anything printed;
- `operation`: the pyinfra operation `network_in_effect` and its facts: stage,
  validate on the host, apply detached from SSH;
- `confirm`: the controller's side at execution time: connect at the new address
  and confirm, or find the host back at its old one and report the rollback;
- `apply`: the script uploaded to the host and run there with the host's python3
  (standard library only, no roslab imports): validate, back up, install, apply,
  wait for the confirmation, roll back without it. It also defines what both sides
  share: layout names, the plan (`Plan`), the status (`Status`), the host's paths;
- `state`: where each host was last confirmed reachable, kept beside the roster
  (`last_known_address`, `record_address`).
"""
