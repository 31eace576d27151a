"""The `matfit` process: Ctrl-C handling first, then the command line (`python -m matfit` and the console script)."""

from matfit import interrupt


def main() -> None:
    """Console-script entry point: installs the interruption watchdog before any heavy import, then runs the command.

    The process then ends without the interpreter's teardown (`interrupt.leave`).
    """
    interrupt.install()
    try:
        from matfit.app.cli import app

        app()
    except KeyboardInterrupt:  # during start-up, before a command took over
        interrupt.exit_now()
    except SystemExit as exit:
        if exit.code == interrupt.EXIT_CODE:
            interrupt.exit_now()
        if exit.code is None or isinstance(exit.code, int):
            interrupt.leave(exit.code or 0)
        raise


if __name__ == "__main__":
    main()
