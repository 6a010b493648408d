"""Analysis probes behind the bench scripts of the same names (the experiment log cites their figures).

Outside the package: openfly_agent never imports them; they may import any of its parts.
"""
