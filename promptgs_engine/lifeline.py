"""Stop when the program that started this process is gone.

A client (the Blender add-on) that starts ``promptgs`` with ``PROMPTGS_LIFELINE=stdin``
in the environment gives it a pipe as standard input and never writes to it. While the
client lives the pipe stays open; when the client exits, however it ends (a crash, a
kill), the operating system closes its end and a read here returns end-of-file. Then
the main thread gets a KeyboardInterrupt, as on a cancel (the last checkpoint and
snapshot are kept), and if it has not exited ``GRACE_S`` seconds later (a long C++ call,
a collective waiting for a peer) the process ends itself.

Every process of a run inherits the same pipe and the variable: ``train --nproc``'s
launcher, torchrun's ranks (torchrun passes its stdin on), so all of them stop.
"""

from __future__ import annotations

import _thread
import os
import sys
import threading
import time

ENV = "PROMPTGS_LIFELINE"
GRACE_S = 5.0


def watch_from_env(environ=os.environ) -> bool:
    """Start the watch when the environment asks for it (``PROMPTGS_LIFELINE=stdin``)."""
    if environ.get(ENV) != "stdin":
        return False
    try:
        fd = sys.stdin.fileno()
    except (AttributeError, OSError, ValueError):  # no usable stdin: nothing to watch
        return False
    threading.Thread(target=_watch, args=(fd,), name="promptgs-lifeline", daemon=True).start()
    return True


def _watch(fd: int, grace_s: float = GRACE_S) -> None:
    try:
        while os.read(fd, 4096):  # the client never writes; data would only be ignored
            pass
    except OSError:
        pass
    print("promptgs: the program that started this run is gone; stopping", file=sys.stderr, flush=True)
    _thread.interrupt_main()
    time.sleep(grace_s)
    os._exit(130)
