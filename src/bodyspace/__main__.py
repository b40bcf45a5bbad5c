"""``python -m bodyspace``: the same as the ``bodyspace`` command."""

from bodyspace.cli import app

app(prog_name="bodyspace")
