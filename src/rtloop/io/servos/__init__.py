"""Smart servo buses: Dynamixel Protocol 2.0 and Feetech SCS/STS over a serial line.

- :mod:`.protocol`: the two wire protocols (packets, CRC-16 or checksum, byte stuffing), the
  hot-path sync write and sync read built once, and the status parser both sides share;
- :mod:`.tables`: control-table addresses and the servo models rtloop knows (units, limits);
- :mod:`.bus`: the device kinds ``dynamixel`` and ``feetech`` (one sync write and one sync
  read per cycle for every servo on the bus; torque off or a declared hold as the safe state);
- :mod:`.model`: servos that speak the real protocol (control table, motor, fault injection),
  served on a pseudo-terminal by :mod:`.emulator` (``rtloop emulate``) and, in process, the
  device's twin (:mod:`.twin`) for ``rtloop simulate``.
"""
