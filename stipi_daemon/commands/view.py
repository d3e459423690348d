"""``stipi-daemon view SESSION``: the live view's page over a stored session.

Thin shell over :func:`stipi_daemon.app.liveview.replay.serve_session`: serves the page
on loopback (``--host`` another address, with a warning) with a random token in the
printed address, until Ctrl-C. The page scrubs through the session video with the force
and S_k traces in step and marks the frames that set S_0, S_max and T_r. A session is an
id under ``--root`` (default: the ``storage.root`` of ``--config``, else ``./sessions``) or
a path to its directory; it is only read.
"""

from __future__ import annotations

import argparse

from stipi_daemon.commands import add_sessions_root


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "view",
        help="serve a stored session's view in the browser (scrub the video with the traces)",
        description=(
            "Serve the view of a stored session for a browser: scrub through its video with "
            "the force and S_k traces and the phases in step, the frames that set S_0, S_max "
            "and T_r marked. Listens on loopback; open the printed address (it holds a "
            "random token). Ctrl-C stops it."
        ),
    )
    parser.add_argument(
        "session", metavar="SESSION", help="session id under --root, or a directory"
    )
    add_sessions_root(parser)
    parser.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on (default 127.0.0.1; another one lets other machines "
        "connect: a warning is printed)",
    )
    parser.add_argument(
        "--port", type=int, default=0, help="TCP port (default 0: a free one, printed)"
    )
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from stipi_daemon.app.config import find_session, sessions_root
    from stipi_daemon.app.liveview.replay import serve_session

    root = sessions_root(args.root, getattr(args, "config", None))
    return serve_session(find_session(root, args.session), args.host, args.port)
