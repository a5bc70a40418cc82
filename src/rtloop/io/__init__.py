"""Devices: hardware a task reads and writes every cycle (GPIO, CAN, SPI, serial, I2C).

``device.py`` is the seam every driver implements; ``limits.py`` guards commands;
``host.py`` runs a task's devices inside its process; ``twin.py`` puts a model in a
device's place for ``rtloop simulate``.
"""
