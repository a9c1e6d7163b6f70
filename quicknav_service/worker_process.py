"""A supervised worker process (started by ``quicknav_service.supervisor``; settings from QUICKNAV_* variables).

    python -m quicknav_service.worker_process --id WORKER_ID --parent PID

SIGTERM stops it after the current unit, handing its job back; it also stops when its parent
(the API process) is gone, so no worker outlives the service that started it.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import threading

from quicknav_service import redact
from quicknav_service.settings import Settings, make_store
from quicknav_service.worker import Worker


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m quicknav_service.worker_process")
    parser.add_argument("--id", required=True, help="the worker id jobs are claimed under")
    parser.add_argument("--parent", type=int, default=None, help="stop when this pid is gone")
    args = parser.parse_args(argv)
    settings = Settings()
    redact.install(settings)  # before logging takes hold of stderr
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    worker = Worker(make_store(settings), settings, worker_id=args.id)

    def stop(signum, frame):
        worker.shutdown.set()

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    if args.parent is not None:

        def orphan_watch():
            while not worker.shutdown.wait(1.0):
                if os.getppid() != args.parent:
                    logging.getLogger("quicknav.worker").warning("parent gone: stopping")
                    worker.shutdown.set()

        threading.Thread(target=orphan_watch, name="parent-watch", daemon=True).start()
    worker.run_forever()


if __name__ == "__main__":  # pragma: no cover
    main()
