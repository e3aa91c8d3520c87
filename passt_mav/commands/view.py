"""passt-mav view: Serve the live view of a run directory (a finished run, or one still flying)."""

from __future__ import annotations

import argparse

HELP = "Serve the live view of a run directory (a finished run, or one still flying) on a local web page"
EXAMPLES = """examples:

    passt-mav view runs/demo-2026-01-01T10-00-00Z              # http://127.0.0.1:<free port>/
    passt-mav view runs/cyl1 --port 8765
    passt-mav view runs/cyl1 --view-host 0.0.0.0 --port 8765   # other machines: a token is printed

    passt-mav run missions/north_atlantic.yaml --view 8765      # the same page while a mission flies
    passt-mav demo --boats 3                                    # the demo serves it by default

The page (no browser is launched; open the address it prints) reads only the run directory: the
estimate (speed, posterior std), land, geofence, tracks, samples, planned paths, reward map, a panel
per boat and the alerts. Everything it loads comes from this server (no internet needed).
"""


def port(text: str) -> int:
    """An argparse type: a TCP port 0..65535 (0 = any free one)."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a port number: {text!r}") from None
    if not 0 <= n <= 65535:
        raise argparse.ArgumentTypeError(f"a port is 0..65535, got {n}")
    return n


class _ViewAction(argparse.Action):
    """``--view [PORT][,optional]``: sets ``view`` (the port, 0 = a free one) and ``view_optional`` (a view that
    cannot start does not stop the run)."""

    def __call__(self, parser, namespace, values, option_string=None):
        parts = [x.strip() for x in (values or "").split(",") if x.strip()]
        optional = "optional" in parts
        nums = [x for x in parts if x != "optional"]
        if len(nums) > 1 or parts.count("optional") > 1:
            parser.error(f"--view takes PORT, optional or PORT,optional; got {values!r}")
        try:
            n = port(nums[0]) if nums else 0
        except argparse.ArgumentTypeError as exc:
            parser.error(f"--view: {exc}")
        setattr(namespace, self.dest, n)
        namespace.view_optional = optional


def add_view_options(p: argparse.ArgumentParser, *, port_flag: str = "--view") -> None:
    """``--view [PORT][,optional]`` and ``--view-host HOST`` (used by run; demo has its own --view)."""
    if port_flag == "--view":
        p.add_argument(
            "--view",
            nargs="?",
            action=_ViewAction,
            const="",
            default=None,
            metavar="PORT",
            help="serve the live view (the operator's console) on 127.0.0.1:PORT (no PORT: a free one); the "
            "address, with the run's token, is printed. A view that cannot start (the port is busy) stops the "
            "run before it connects (exit 2) unless 'optional' is given: --view optional, --view 8765,optional",
        )
        p.set_defaults(view_optional=False)
    p.add_argument(
        "--view-host",
        default="127.0.0.1",
        metavar="HOST",
        help="address to bind the view to (default 127.0.0.1); any other needs the token printed at start",
    )


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir", metavar="RUN_DIR", help="run directory (written by passt-mav run / demo)")
    p.add_argument("--port", type=port, default=0, help="TCP port (default: a free one)")
    add_view_options(p, port_flag="--port")


def start_live_view(run_dir, port: int, host: str, echo=print, *, required: bool = False):
    """The view of ``run_dir`` in a subprocess (:func:`passt_mav.view.start_view`), its address printed;
    None (said in one line) when it cannot start: the mission goes on without it. ``required``: raise
    :class:`~passt_mav.errors.UserError` instead (``run --view`` without ``optional``)."""
    from passt_mav.view import start_view

    try:
        vp = start_view(run_dir.root, port=port, host=host, log_file=run_dir.root / "view.log")
    except OSError as exc:
        if required:
            from passt_mav.errors import UserError

            raise UserError(
                f"the live view did not start ({exc}); nothing flown (--view {port or ''},optional goes on without it)"
            ) from None
        echo(f"live view: not started ({exc}); the mission goes on without it")
        return None
    echo(f"live view: {vp.url}  (a local page; open it in a browser)")
    return vp


def run(args: argparse.Namespace) -> int:
    import threading

    from passt_mav.errors import UserError
    from passt_mav.runs.rundir import RunDir
    from passt_mav.view import new_token, view_address

    rd = RunDir(args.run_dir)
    if not rd.is_run_dir():
        raise UserError(f"{args.run_dir} is not a run directory (no summary.json, samples, legs or events)")
    from passt_mav.view.server import serve

    token = new_token()
    from passt_mav.view import check_port

    try:
        check_port(args.view_host, args.port)
    except OSError as exc:
        raise UserError(f"--port: {exc}; choose another port") from None

    def ready(port: int) -> None:
        print(f"live view of {rd.root}: {view_address(args.view_host, port, token)}  (Ctrl-C stops it)", flush=True)

    threading.current_thread().name = "view"
    serve(rd.root, host=args.view_host, port=args.port, token=token, on_ready=ready)
    return 0
