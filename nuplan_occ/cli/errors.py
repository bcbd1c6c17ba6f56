"""The top-level error handler of the `nuplan-occ` and `occgen` command lines.

An expected failure (bad or missing input, a refused pickle, a bad config, a dataset that breaks the
format) ends the command with ONE line on stderr, `<prog>: error: <file>: <problem>`, and exit code 1.
The global option `--debug` (before the command: `nuplan-occ --debug stats out/`) re-raises instead,
so the full traceback is shown. Anything else (a bug) always shows its traceback. A warning about
damaged input the command skipped (`storage.errors.DamagedManifestWarning`) is one line on stderr,
`<prog>: warning: <file>: <problem>`.
"""

from __future__ import annotations

import sys
import warnings
from typing import Any

import typer


def expected_errors() -> tuple[type[BaseException], ...]:
    """Failures caused by the user's input or environment, not by a bug (OSError: missing or unreadable
    files). Imported when an error happens, so the CLI starts without loading these modules."""
    from nuplan_occ.evaluation.datasets import EvaluationError
    from nuplan_occ.export.formats import ExportError
    from nuplan_occ.io.errors import NuplanFormatError
    from nuplan_occ.pipeline.executors import ExecutorError
    from nuplan_occ.pipeline.params import ConfigError
    from nuplan_occ.recon.params import ReconError
    from nuplan_occ.storage.errors import StorageError

    return (NuplanFormatError, StorageError, ConfigError, ExecutorError, ExportError, EvaluationError, ReconError,
            OSError)


def one_line(exc: BaseException) -> str:
    """The error as one line naming the file and the problem (OSError: `<file>: <reason>`)."""
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        message = f"{exc.filename}: {exc.strerror.lower()}"
    else:
        message = str(exc) or type(exc).__name__
    return " ".join(part.strip() for part in message.splitlines() if part.strip())


class CliApp(typer.Typer):
    """A typer app with the global `--debug` option whose expected failures (`expected_errors()` plus
    `extra_errors`) end as one line `<prog>: error: ...` on stderr and exit code 1 (see module docstring)."""

    def __init__(self, prog: str, *, extra_errors: tuple[type[BaseException], ...] = (), **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.prog, self.extra_errors, self.debug = prog, extra_errors, False

        @self.callback()
        def _global_options(debug: bool = typer.Option(
                False, "--debug", help="Show the full traceback of an error instead of one line.")) -> None:
            self.debug = debug

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        from nuplan_occ.storage.errors import DamagedManifestWarning

        shown = warnings.showwarning

        def show(message, category, *rest: Any, **options: Any) -> None:
            if issubclass(category, DamagedManifestWarning):
                print(f"{self.prog}: warning: {one_line(message)}", file=sys.stderr)
            else:
                shown(message, category, *rest, **options)

        try:
            with warnings.catch_warnings():
                warnings.showwarning = show
                return super().__call__(*args, **kwargs)
        except Exception as exc:
            if self.debug or not isinstance(exc, expected_errors() + self.extra_errors):
                raise
            print(f"{self.prog}: error: {one_line(exc)}", file=sys.stderr)
            sys.exit(1)
