"""One module per ``mushroom-pose`` command, each with ``add_parser(subparsers)`` and ``run(args) -> int``.

Building a parser imports nothing heavy; each ``run`` imports the libraries its command needs."""
