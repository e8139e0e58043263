"""`python -m ttmjx ARGS`: the `ttmjx` console script itself (ttmjx.entry), for a source tree
that is not installed (the GPU machines' scripts) and for tests that need a fresh process."""
from ttmjx.entry import main

main()
