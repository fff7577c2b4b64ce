"""The `roslab` command and its subcommands (status, verify, init, trust, forget...); roslab.reach is how each takes ROSTER/--limit."""
