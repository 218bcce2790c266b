"""The command line: one thin module per command group (parse, call, print).

`main.py` assembles the `autopower` group; each other module holds one group of commands
(analysis, simulate, team processes, operator commands, faults, demo, replay). Commands report
errors through `entry.py`: one line, exit status 2, never a traceback.

May import every other package; nothing imports this.
"""
