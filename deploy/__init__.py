"""roslab's pyinfra deploys, one module per concern (deploy.py runs them in order).

Their settings are declared in `roslab.settings` (the schema); each deploy's
`DEFAULTS` is `settings.defaults("<concern>")`.
"""
