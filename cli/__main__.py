"""`python -m sdfzoo.cli ARGS` is `zoo ARGS`."""

from .main import main

main()
