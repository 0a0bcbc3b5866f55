"""The command line: ``deepcharuco detect|calibrate|board|export`` (`main`), their input and output (videos,
folders, cameras, overlays, output files) and what they share (one-line errors, exit codes).

The top of the runtime: imports every other subpackage, and none imports it.
"""

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    """The ``deepcharuco`` command (`deepcharuco.cli.main.main`)."""
    from deepcharuco.cli.main import main as run

    return run(argv)
