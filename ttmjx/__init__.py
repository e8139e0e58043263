"""ttmjx: the simulated world (ttmjx.world), the tools that only use it (ttmjx.tools), the command
line's plumbing (ttmjx.commandline) and, on top of every package, the command line (ttmjx.cli,
reached through the console script's entry, ttmjx.entry)."""
