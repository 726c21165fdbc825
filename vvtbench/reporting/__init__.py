"""Reporting: figures and the leaderboard drawn from results tables.

* :mod:`vvtbench.reporting.plots`: material fields, sweeps and resolution figures.
* :mod:`vvtbench.reporting.leaderboard`: Markdown and static HTML from a results table.
"""
