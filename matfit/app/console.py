"""The command line's conventions, shared by every command: one-line errors, interruptions, option names in messages.

A command's fixable error (`errors.MatfitError`) and Typer's own usage errors become one `error:`
line and exit code 2; Ctrl-C or `kill` one `interrupted:` line and exit code 130 (`interrupt`
enforces it when the work is stuck in compiled code); an operating-system failure such as a full
disk one `error:` line and exit code 1. An error about one value (`MatfitError.field`, in the
library's words) is reworded with the option the user typed. A reader of standard output that has
gone (`matfit params | head -1`) ends the command quietly with exit code 141, as a Unix tool killed
by SIGPIPE does.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import os
import re
import select
import sys
import typing

import typer
from typer.core import TyperGroup

from matfit import errors, interrupt

FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)  # the disk is full, or a quota or a size limit is reached
CLOSED_PIPE_EXIT_CODE = 141  # 128 + SIGPIPE: what the shell reports for a tool whose reader went away


class OneLineErrors(TyperGroup):
    """Typer's command group, with usage errors (an unknown option, `--evals abc`) as one `error:` line, exit 2."""

    def main(
        self, args=None, prog_name=None, complete_var=None, standalone_mode=True, windows_expand_args=True, **extra
    ):
        arguments = list(sys.argv[1:] if args is None else args)
        try:
            code = super().main(
                arguments,
                prog_name,
                complete_var,
                standalone_mode=False,
                windows_expand_args=windows_expand_args,
                **extra,
            )
        except typer._click.exceptions.NoArgsIsHelpError as error:
            typer.echo(error.format_message())
            code = 0
        except typer._click.exceptions.UsageError as error:
            typer.echo(f"error: {usage_message(error, arguments)}", err=True)
            code = 2
        except typer.Abort:  # a Ctrl-C outside a command's own work (while parsing, say)
            interrupt.announce()
            code = interrupt.EXIT_CODE
        except SystemExit as exit:  # Click's own answer to a closed pipe while it prints help: exit 1
            if exit.code != 1 or not stdout_closed():
                raise
            code = quiet_exit()
        if not standalone_mode:
            return code
        sys.exit(code if isinstance(code, int) else 0)


def usage_message(error, arguments: list[str]) -> str:
    """Returns a usage error as one line that names the option, the value given and what it takes."""
    message = error.message.removeprefix("Value error, ")
    param = getattr(error, "param", None)
    if isinstance(error, typer._click.exceptions.MissingParameter) and param is not None and not message:
        return missing_message(param, error.ctx)
    if param is None or not getattr(param, "opts", None):
        return message
    flag = max(param.opts, key=len)
    given = next((arguments[k + 1] for k, a in enumerate(arguments[:-1]) if a in param.opts), None)
    low, high = getattr(param, "min", None), getattr(param, "max", None)
    if given is not None and (low is not None or high is not None) and "than or equal" in message:
        limits = (
            f"use {low} to {high}"
            if low is not None and high is not None
            else f"use {low} or more"
            if high is None
            else f"use {high} or less"
        )
        return f"{flag} {given} is out of range: {limits}"
    return f"{flag} {given}: {message}" if given is not None else f"{flag}: {message}"


def missing_message(param, ctx) -> str:
    """Returns the line for a command's argument left out (`matfit fit` alone): what the argument is, after its help's
    first words ("The edited picture: PNG, ..." -> "the edited picture"), and where to read more."""
    command = f"matfit {ctx.info_name}" if ctx is not None and ctx.info_name else "the command"
    what = re.split(r"[:.(]", getattr(param, "help", None) or "")[0].strip()
    what = what[:1].lower() + what[1:] if what else param.name.replace("_", " ")
    what = what if what.startswith(("the ", "a ", "an ")) else f"the {what}"
    return f"{command} needs {what}: give its path (`{command} --help` says more)"


def flags(function) -> dict[str, str]:
    """Returns {parameter name: the option the user types} of a command function, e.g. {"evaluations": "--evals"}."""
    names = {}
    for name, hint in typing.get_type_hints(function, include_extras=True).items():
        for info in getattr(hint, "__metadata__", ()):
            if isinstance(info, typer.models.OptionInfo):
                declared = [info.default] if isinstance(info.default, str) and info.default.startswith("-") else []
                declared += list(info.param_decls or ())
                long = [flag for flag in declared if flag.startswith("--")]
                names[name] = long[0] if long else "--" + name.replace("_", "-")
    return names


def command(app: typer.Typer, function=None, *, name: str | None = None, interrupted: str = "nothing was written"):
    """Registers a command: fixable errors become one `error:` line (exit 2), Ctrl-C one `interrupted:` line (exit 130).

    An error about one value (`MatfitError.field`) is reworded with the option the user typed; a
    failure of the system (OSError: a full disk, a vanished directory) is one `error:` line, exit 1.
    `interrupted` says what an interruption leaves behind.
    """
    if function is None:
        return functools.partial(command, app, name=name, interrupted=interrupted)
    options = flags(function)

    @functools.wraps(function)
    def wrapper(*args, **kwargs):
        interrupt.set_message(interrupted)
        try:
            return function(*args, **kwargs)
        except errors.MatfitError as error:
            typer.echo(f"error: {with_flag(str(error), error.field, options)}", err=True)
            raise typer.Exit(2) from None
        except BrokenPipeError as error:
            if not stdout_closed():  # another pipe (a child process's) is a failure to report
                typer.echo(f"error: {system_message(error)}", err=True)
                raise typer.Exit(1) from None
            raise typer.Exit(quiet_exit()) from None
        except OSError as error:
            typer.echo(f"error: {system_message(error)}", err=True)
            raise typer.Exit(1) from None
        except KeyboardInterrupt:
            typer.echo(f"interrupted: {interrupted}", err=True)
            interrupt.announced()
            raise typer.Exit(interrupt.EXIT_CODE) from None

    return app.command(name=name)(wrapper)


def stdout_closed() -> bool:
    """Returns whether standard output is a pipe whose reader has gone (poll reports an error on its end)."""
    try:
        descriptor = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # not a file (a test's captured output)
        return False
    poller = select.poll()
    poller.register(descriptor, select.POLLOUT)
    return any(events & select.POLLERR for _, events in poller.poll(0))


def quiet_exit() -> int:
    """Points standard output at /dev/null (so that no later flush fails again) and returns the exit code 141."""
    with contextlib.suppress(OSError, ValueError):
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, sys.stdout.fileno())
        os.close(null)
    return CLOSED_PIPE_EXIT_CODE


def system_message(error: OSError) -> str:
    """Returns an operating-system failure as one line: what failed, on which file."""
    reason = error.strerror or str(error)
    where = f" ({errors.printable(error.filename)})" if error.filename else ""
    return f"{reason}{where}: free some space or choose another place" if error.errno in FULL else f"{reason}{where}"


def with_flag(message: str, field: str | None, options: dict[str, str]) -> str:
    """Returns a library message with its leading field ("evaluations 5 ...") as the option typed ("--evals 5 ...")."""
    if field is None or field not in options:
        return message
    words = field.replace("_", " ")
    return options[field] + message[len(words) :] if message.startswith(words) else message


def echo_lines(lines) -> None:
    """Prints notices to standard error, one per line."""
    for line in lines:
        typer.echo(line, err=True)
