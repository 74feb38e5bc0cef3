"""The ``latentz`` command line.

Every command ends bad input with one clear line on stderr and a non-zero exit status, never a
traceback, and writes its outputs atomically.
"""

from __future__ import annotations

import sys
from pathlib import Path

import click

from latentz import __version__

EXIT_BAD_INPUT = 2


class _Group(click.Group):
    """A click group that turns expected errors into one line on stderr."""

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except (click.exceptions.Exit, click.exceptions.Abort, click.ClickException):
            raise
        except (ValueError, TypeError, FileNotFoundError, OSError, KeyError) as exc:
            message = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            click.echo(f"latentz: error: {message}", err=True)
            sys.exit(EXIT_BAD_INPUT)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="latentz")
def main() -> None:
    """latentz: accurate 3D localization microscopy by intrinsic aberration calibration."""


@main.command()
@click.argument("kind", type=click.Choice(["calibration", "gear", "apertures"]))
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Folder for the TIFF stacks, ground-truth CSV and metadata JSON.",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed.")
@click.option("--quick", is_flag=True, help="A small dataset, for a fast look.")
@click.option("--plot", is_flag=True, help="Also write the PSF gallery PNG.")
def simulate(kind: str, out_dir: Path, seed: int, quick: bool, plot: bool) -> None:
    """Simulate a dataset with ground truth: calibration stacks, a gear movie or apertures."""
    from latentz.simulate import write_dataset

    written = write_dataset(kind, out_dir, seed=seed, quick=quick, plot=plot)
    for path in written:
        click.echo(str(path))


if __name__ == "__main__":  # pragma: no cover
    main()
