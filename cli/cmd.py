"""``neso cmd``: one command to a running service (lives with ``neso params``)."""
from cli.params import add_cmd_parser as add_parser, run_cmd as run  # noqa: F401
