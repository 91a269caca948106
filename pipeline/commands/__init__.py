"""One module per ``mushroom-pose`` command, each with ``NAME``, ``HELP``, ``add_arguments(parser)`` and
``run(args) -> int`` (``pipeline.cli.COMMANDS`` lists them).

Building a parser imports nothing heavy; each ``run`` imports the libraries its command needs."""
