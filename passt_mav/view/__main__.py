"""``python -m passt_mav.view RUN_DIR --host H --port P``: the view server (token from $PASST_VIEW_TOKEN)."""

from __future__ import annotations

import argparse
import os
import sys


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m passt_mav.view")
    p.add_argument("root")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=0)
    p.add_argument(
        "--exit-with-parent",
        action="store_true",
        help="stop when the process that started this one is gone (the mission's: never an orphan)",
    )
    a = p.parse_args(argv)
    if a.exit_with_parent:
        _watch_parent(os.getppid())
    from passt_mav.view import TOKEN_ENV, new_token
    from passt_mav.view.server import serve

    serve(a.root, host=a.host, port=a.port, token=os.environ.get(TOKEN_ENV) or new_token())
    return 0


def _watch_parent(parent: int) -> None:
    import threading
    import time

    def watch():
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(0)

    threading.Thread(target=watch, name="watch-parent", daemon=True).start()


if __name__ == "__main__":
    sys.exit(main())
