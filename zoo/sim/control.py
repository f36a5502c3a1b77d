"""Waypoints: mocap bodies' positions and actuators' controls at given times, interpolated linearly between them.

A scene's ``[[control]]`` entries (or :class:`Waypoints` built in Python) drive a robot the way a script
would: each entry has a ``time`` (s) and any of ``mocap = {body: [x, y, z]}`` (a mocap body's world
position) and ``ctrl = {actuator: value}``. Before each step the targets at the step's time are written
into ``data.mocap_pos`` and ``data.ctrl``; before the first entry its values hold, after the last entry
the last values hold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError

KEYS = {"time", "mocap", "ctrl"}


@dataclass
class Track:
    """One target over time: ``times`` (T,) ascending and ``values`` (T, D)."""

    times: np.ndarray
    values: np.ndarray

    def at(self, t: float) -> np.ndarray:
        """(D,) the value at time ``t``, linear between waypoints and held outside them."""
        return np.array([np.interp(t, self.times, self.values[:, k]) for k in range(self.values.shape[1])])


class Waypoints:
    """Targets for a model's mocap bodies and actuators (see the module docstring).

    Args:
        model: the ``mujoco.MjModel`` whose names the entries use.
        entries: a list of {"time": t, "mocap": {body: (3,)}, "ctrl": {actuator: value}}.
    """

    def __init__(self, model, entries: list[dict]):
        import mujoco

        if not entries:
            raise InputError("waypoints need at least one entry with a time")
        for entry in entries:
            unknown = set(entry) - KEYS
            if unknown or "time" not in entry:
                raise InputError(f"a control entry has keys {sorted(entry)}; it needs a time and may have {sorted(KEYS - {'time'})}")
        entries = sorted(entries, key=lambda e: float(e["time"]))
        self.mocap: dict[int, Track] = {}
        self.ctrl: dict[int, Track] = {}
        for key, kind, table in (("mocap", mujoco.mjtObj.mjOBJ_BODY, self.mocap), ("ctrl", mujoco.mjtObj.mjOBJ_ACTUATOR, self.ctrl)):
            names = sorted({name for e in entries for name in e.get(key, {})})
            for name in names:
                index = mujoco.mj_name2id(model, kind, name)
                if index < 0:
                    raise InputError(f"control names {key} {name!r}, which the model does not have")
                if key == "mocap":
                    index = int(model.body_mocapid[index])
                    if index < 0:
                        raise InputError(f"control moves body {name!r}, which is not a mocap body (mocap=\"true\")")
                rows = [(float(e["time"]), np.atleast_1d(np.asarray(e[key][name], dtype=np.float64))) for e in entries if name in e.get(key, {})]
                width = 3 if key == "mocap" else 1
                if any(v.shape != (width,) for _, v in rows):
                    raise InputError(f"control {key} {name!r}: every value must have {width} number(s)")
                table[index] = Track(np.array([t for t, _ in rows]), np.stack([v for _, v in rows]))

    def apply(self, data, t: float) -> None:
        """Write the targets at time ``t`` into ``data.mocap_pos`` and ``data.ctrl``."""
        for index, track in self.mocap.items():
            data.mocap_pos[index] = track.at(t)
        for index, track in self.ctrl.items():
            data.ctrl[index] = track.at(t)[0]
