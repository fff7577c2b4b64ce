"""Checked input, below every other concern: what a problem is and how a YAML file is read.

    problems.py   Problem, Report, RosterError: every problem names file:line, team, host, field
    loading.py    strict, bounded YAML reading (duplicate keys, lines, alias bombs, encodings)

The roster, the profiles, the sources' .repos files and the settings all report through these,
so none of them needs another's folder to say what is wrong.
"""
