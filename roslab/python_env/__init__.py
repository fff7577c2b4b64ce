"""The robot profiles' Python: a venv per login user, from a wheelhouse the controller fills once."""
