"""One-off investigations and reference scripts: profiles and measurements behind docs/*.md, run from a clone.

Not shipped (setup.py installs zoo and sdfzoo.* only): what a user runs is `zoo bench`, `zoo stress` and
`zoo demo`. Each module here has ``main(argv)`` and writes its JSON through :mod:`investigations.report`;
the one way to run them is the runner, from the clone's root::

    python -m investigations                 # the list, one line each
    python -m investigations NAME [ARGS]     # one of them; NAME --help for its options

Imports run one way: investigations -> sdfzoo.benches -> sdfzoo.pipeline -> zoo.
"""
