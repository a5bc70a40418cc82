"""The twin of a drive device (``kind = "ethercat"``, and ``"canopen402"``'s too): the same
:class:`~rtloop.io.drives.cycle.DriveCycle` as the device, exchanging with the emulated drives'
models in process, so ``rtloop simulate`` of an app equals its run against the emulated drives bit
for bit (up to the first miss)."""

from __future__ import annotations

from typing import Any

from rtloop.io.device import FloatVector
from rtloop.io.drives.cycle import DriveCycle
from rtloop.io.drives.drive_model import DriveModel
from rtloop.io.drives.joints import JointConfig
from rtloop.runnable import Runnable

__all__ = ["EthercatTwin"]


class EthercatTwin(Runnable):
    """The device's twin: the same :class:`DriveCycle` exchanging with the emulated drives in process,
    as the emulated slaves answer an LRW (the inputs they hold, then a step with the outputs)."""

    def __init__(self, device: Any) -> None:
        """``device``: an EtherCAT or CANopen drive device (its name, joints and signal names)."""
        self.device_name = device.name
        self.joints: tuple[JointConfig, ...] = device.joints
        self.n_inputs, self.n_outputs = device.n_inputs, device.n_outputs
        self.input_names, self.output_names = device.input_names, device.output_names
        # the EtherCAT device's frame_ok (lost_frames_max): the twin's frames always come
        self.frame_ok_at = self.n_outputs - 1 if self.output_names[-1:] == ("frame_ok",) else -1

    def prerun(self) -> None:
        from rtloop.io.drives.esc import tx_values

        self._tx_values = tx_values
        self.cycle = DriveCycle(self.device_name, self.joints)
        self.drives = [DriveModel(joint.drive) for joint in self.joints]
        self.outputs = bytearray(self.cycle.output_bytes)
        self.inputs = bytearray(self.cycle.input_bytes)
        self.cycle.bind(self.outputs, 0, self.inputs, 0)
        self._publish()

    def _publish(self) -> None:
        at = 0
        for joint, drive in zip(self.joints, self.drives, strict=True):
            joint.tx.struct.pack_into(self.inputs, at, *self._tx_values(drive, joint.tx))
            at += joint.tx.size

    def _exchange(self) -> None:
        self._publish()  # the answer carries what the drives held when the frame passed
        at = 0
        for joint, drive in zip(self.joints, self.drives, strict=True):
            values = joint.rx.struct.unpack_from(self.outputs, at)
            rx = joint.rx.position

            def get(index: int, default: int, values: tuple[Any, ...] = values, rx: dict[int, int] = rx) -> int:
                return int(values[rx[index]]) if index in rx else default

            drive.exchange(get(0x6040, 0), get(0x6060, drive.mode), get(0x607A, 0), get(0x60FF, 0), get(0x6071, 0))
            drive.events.clear()
            at += joint.rx.size

    def step(self, u: FloatVector, y: FloatVector) -> None:
        self.cycle.prepare_outputs(u)
        self._exchange()
        self.cycle.take_inputs(y)
        if self.frame_ok_at >= 0:
            y[self.frame_ok_at] = 1.0
