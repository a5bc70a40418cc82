"""The FPGA model answering on the SPI bus: one model step per transfer, served from user space.

In the PREEMPT_RT test guest the project's SPI controller (``tools/rtkernel/spi_loopback.c``)
hands every transfer on chip select 1 (``/dev/spidev0.1``) to the process holding
``/dev/rtloop_spi_serve`` open: a ``read`` gives the bytes the controller sent (one whole
transfer), a ``write`` of as many bytes is what the controller receives. This server is that
process for ``examples/jiwy_spi``: it decodes each frame (CRC-checked) into the commands, steps
the FPGA model (``jiwy_spi_models.FpgaModel``, the SPI device's twin) on them once, and answers
with the model's encoder counts and status, the counter of the frame before and the CRC (the
protocol: README.md). Every exchange the device makes is one step, configure's safe frame before
T0 included, as the twin steps in ``rtloop simulate``: the run equals the simulation bit for bit
up to its first deadline miss.

    .venv/bin/python examples/jiwy_spi/fpga_server.py --log fpga.csv &
    rtloop run examples/jiwy_spi/jiwy_spi.toml ... (with device = "/dev/spidev0.1")

``--log`` writes one row per transfer as the model's side saw it (the commands the wire carried,
whether the frame was good, what was answered): the E-stop's last frame, PWM 0 and enable off,
is read back there. SIGTERM or SIGINT ends it; the controller then finds nobody answering (its
transfers receive 0xFF bytes: a bad CRC).
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
from pathlib import Path
from typing import IO

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from jiwy_spi_models import FRAME_LENGTH, FpgaModel

from rtloop.io.spiframe import crc16_ccitt, seal

SERVE_DEVICE = "/dev/rtloop_spi_serve"
LOG_HEADER = "transfer,counter,good,pwm_pan,pwm_tilt,enable,encoder_pan,encoder_tilt,status,answered\n"


class FpgaServer:
    """The FPGA's side of each transfer: the frame received → one model step → the frame answered."""

    def __init__(self, model: FpgaModel, log: IO[str] | None = None) -> None:
        self.model = model
        self.log = log
        self.transfers = 0
        self.bad_frames = 0
        self.previous_counter = 0  # the counter of the frame before ("previous"): none before the first
        self.commands = np.zeros(3)  # [pwm_pan, pwm_tilt, enable] as the last good frame carried them
        self.readings = np.zeros(3)
        self.last_good = False  # whether the last frame received passed its checks
        self.answer = bytearray(FRAME_LENGTH)
        self._answer_crc_view = memoryview(self.answer)[:FRAME_LENGTH - 2]
        if log is not None:
            log.write(LOG_HEADER)

    def exchange(self, sent: bytes) -> bytearray:
        """The answer to one transfer. A frame of the wrong length or with a bad CRC is not obeyed
        (the commands stay the last good ones), as an FPGA that checks its frames would; the model
        still steps: the motors turn on whatever the bridges were last told."""
        good = len(sent) == FRAME_LENGTH and crc16_ccitt(sent[:-2]) == int.from_bytes(sent[-2:], "big")
        counter = sent[0] if sent else 0
        self.last_good = good
        if good:
            self.model.send.unpack_from(sent, 0, self.commands)
        else:
            self.bad_frames += 1
        self.model.step(self.commands, self.readings)
        answer = self.answer
        answer[:] = self.model.answer
        seal(answer, self._answer_crc_view, self.previous_counter)
        if good:
            self.previous_counter = counter
        self.transfers += 1
        return answer

    def record(self, sent: bytes, answered: bool) -> None:
        """One row of the log: the transfer as the model's side saw it."""
        if self.log is None:
            return
        c, r = self.commands.tolist(), self.readings.tolist()  # floats: repr is the exact number
        self.log.write(f"{self.transfers - 1},{sent[0] if sent else -1},{int(self.last_good)},"
                       f"{c[0]!r},{c[1]!r},{c[2]!r},{r[0]!r},{r[1]!r},{r[2]!r},{int(answered)}\n")


def serve(fd: int, server: FpgaServer) -> None:
    """Answer transfers on ``fd`` until it ends (EOF) or a signal stops the process. A transfer that
    gave up waiting (the controller module's timeout) refuses the late answer (ETIMEDOUT): logged."""
    while True:
        try:
            sent = os.read(fd, 4096)
        except InterruptedError:
            continue
        if not sent:
            return
        answer = server.exchange(sent)
        try:
            os.write(fd, answer)
            answered = True
        except TimeoutError:
            answered = False
        server.record(sent, answered)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--serve", default=SERVE_DEVICE,
                        help=f"the controller module's serving device ({SERVE_DEVICE})")
    parser.add_argument("--step-size-s", type=float, default=0.005, help="the model's step (the app's twin_args)")
    parser.add_argument("--log", type=Path, help="one CSV row per transfer, as the model's side saw it")
    parser.add_argument("--priority", type=int, default=0, help="SCHED_FIFO priority (0: not real-time)")
    args = parser.parse_args(argv)

    def stop(signum: int, _frame: object) -> None:
        raise SystemExit(0)

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    try:
        fd = os.open(args.serve, os.O_RDWR | os.O_CLOEXEC)
    except FileNotFoundError:
        print(f"fpga_server: no {args.serve} (the rtloop_spi_loopback module of the test guest serves SPI "
              "transfers there: docs/rtkernel-guest.md)", file=sys.stderr)
        return 3
    except OSError as error:
        print(f"fpga_server: cannot open {args.serve}: {error.strerror} (one server at a time)", file=sys.stderr)
        return 3
    if args.priority:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.priority))
    model = FpgaModel(step_size_s=args.step_size_s)
    model.prerun()
    try:
        with open(args.log or os.devnull, "w", buffering=1) as log:  # line-buffered: readable while it runs
            print(f"fpga_server: answering transfers from {args.serve}", file=sys.stderr, flush=True)
            serve(fd, FpgaServer(model, log if args.log else None))
    finally:
        os.close(fd)
    return 0


if __name__ == "__main__":
    sys.exit(main())
