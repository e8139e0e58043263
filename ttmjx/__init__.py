"""ttmjx: the simulated world (ttmjx.world), the tools that only use it (ttmjx.tools) and, on top of every package, the command line (ttmjx.cli)."""
