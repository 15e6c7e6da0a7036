"""Proprioception read straight from MjData with index arrays resolved once per model.

Each name is a dm_control walker observable; the values equal what that observable
returns for the same physics state (tests check this dimension by dimension). Reading
them through composer's observation updater costs more than the physics step itself.
"""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

SUPPORTED = ("joints_pos", "joints_vel", "end_effectors_pos", "appendages_pos", "body_height",
             "world_zaxis", "sensors_velocimeter", "sensors_gyro", "sensors_accelerometer",
             "actuator_activation")


def _sensor_indices(physics, sensors) -> np.ndarray:
    model = physics.model.ptr
    ids = np.atleast_1d(physics.bind(list(sensors)).element_id)
    return np.concatenate([np.arange(model.sensor_adr[i], model.sensor_adr[i] + model.sensor_dim[i])
                           for i in ids]).astype(np.intp)


def _egocentric_positions(root: int, bodies: np.ndarray) -> Callable:
    def read(data) -> np.ndarray:
        xmat = data.xmat[root].reshape(3, 3)
        return ((data.xpos[bodies] - data.xpos[root]) @ xmat).reshape(-1)
    return read


class Proprioception:
    """Concatenates the configured observables into one float32 vector.

    `slices` maps each name to its place in the vector, so tests and agents can find
    the parts (the paper encodes them all with one linear layer).
    """

    def __init__(self, walker, physics, names: Sequence[str]):
        unknown = [n for n in names if n not in SUPPORTED]
        if unknown:
            raise ValueError(f"body.proprio has unknown observable(s) {unknown}; allowed: {', '.join(SUPPORTED)}")
        self.names = tuple(names)
        root = int(physics.bind(walker.root_body).element_id)
        readers: list[Callable] = []
        for name in names:
            readers.append(self._reader(name, walker, physics, root))
        self._readers = readers
        sizes = []
        probe = physics.data.ptr
        for read in readers:
            sizes.append(int(np.size(read(probe))))
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
        self.slices = {n: slice(offsets[i], offsets[i + 1]) for i, n in enumerate(names)}
        self.size = int(offsets[-1])

    @staticmethod
    def _reader(name: str, walker, physics, root: int) -> Callable:
        model = physics.model.ptr
        if name in ("joints_pos", "joints_vel"):
            joints = list(walker.observable_joints)
            if not joints:
                return lambda data: np.zeros(0)
            ids = np.atleast_1d(physics.bind(joints).element_id)
            adr = model.jnt_qposadr[ids] if name == "joints_pos" else model.jnt_dofadr[ids]
            adr = np.asarray(adr, dtype=np.intp)
            if name == "joints_pos":
                return lambda data: data.qpos[adr]
            return lambda data: data.qvel[adr]
        if name == "end_effectors_pos":
            sensors = list(walker.end_effectors_pos_sensors)
            if sensors:  # dm_control adds framepos sensors for this observable
                idx = _sensor_indices(physics, sensors)
                return lambda data: data.sensordata[idx]
            bodies = np.atleast_1d(physics.bind(list(walker.end_effectors)).element_id).astype(np.intp)
            return _egocentric_positions(root, bodies)
        if name == "appendages_pos":
            bodies = np.atleast_1d(physics.bind(list(walker.end_effectors) + [walker.head]).element_id)
            return _egocentric_positions(root, bodies.astype(np.intp))
        if name == "body_height":
            return lambda data: data.xpos[root, 2:3]
        if name == "world_zaxis":
            return lambda data: data.xmat[root, 6:9]
        if name.startswith("sensors_"):
            sensors = getattr(walker.mjcf_model.sensor, name[len("sensors_"):])
            idx = _sensor_indices(physics, sensors)
            return lambda data: data.sensordata[idx]
        if name == "actuator_activation":
            ids = np.atleast_1d(physics.bind(list(walker.actuators)).element_id)
            adr = np.asarray([model.actuator_actadr[i] for i in ids if model.actuator_actadr[i] >= 0],
                             dtype=np.intp)
            return lambda data: data.act[adr]
        raise AssertionError(name)

    def __call__(self, data, out: np.ndarray | None = None) -> np.ndarray:
        out = np.empty(self.size, np.float32) if out is None else out
        for name, read in zip(self.names, self._readers):
            out[self.slices[name]] = read(data)
        return out
