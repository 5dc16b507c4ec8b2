"""What a controller is to the flight loop (sdexp.control.rollout.fly): the interface every
controller of the paper meets and a new one implements. sdexp.eval.controllers builds them
by name (README "Adding a controller")."""
from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from sdexp.control.tasks import Task
from sdexp.sensing import State


@runtime_checkable
class Controller(Protocol):
    # the flight's label (Flight.controller), the name it is registered and listed under
    name: str

    def reset(self, task: Task) -> None:
        """Before each flight: the task to follow (its goal over time, ``task.goal(t)``)."""

    def act(self, t: float, state: State) -> np.ndarray:
        """The thrust command (one per rotor, N) at time ``t`` from the decomposed sensor
        readings; the loop clips it to the rotors' range. Raising sdexp.control.lqr.LqrFailure (or
        returning a non-finite command) ends the flight as the controller's failure."""
