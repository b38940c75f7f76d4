"""Small helpers shared by the engine's tests (importable: pytest puts this folder on
``sys.path`` when it imports the test modules here)."""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np


def planar_pose(x: float = 0.0, y: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    """A 4x4 pose at ``(x, y, 0)`` turned ``yaw_deg`` about z."""
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[:2, 3] = x, y
    return T


def assert_other_threads_run_during(calls: dict[str, Callable[[], object]]) -> None:
    """Each call, run on a worker thread, lets this thread run Python while it works: the
    line after a short wait finds the worker not done yet, which it could not if the call
    held the interpreter lock until it returned."""
    for name, call in calls.items():
        started, state = threading.Event(), {"done": False}

        def work(call=call, started=started, state=state) -> None:
            started.set()
            call()
            state["done"] = True

        worker = threading.Thread(target=work)
        worker.start()
        started.wait()
        threading.Event().wait(0.02)  # give the worker time to enter the kernel
        running_meanwhile = not state["done"]  # this line needs the lock
        worker.join()
        assert state["done"] and running_meanwhile, name
