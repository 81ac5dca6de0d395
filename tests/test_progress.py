"""The image progress bar of ``detect`` and ``calibrate`` as a terminal shows it: the count,
the time left and the rate (click hides a bar on a stream that is not a terminal, so the test
gives it a pseudo-terminal)."""

import os
import pty
import re
import sys
import time

from zoomcalib import cli


def test_the_progress_bar_shows_count_time_left_and_rate(monkeypatch):
    master, slave = pty.openpty()
    with os.fdopen(slave, "w") as terminal:
        monkeypatch.setattr(sys, "stderr", terminal)
        with cli._image_progress(60, "detecting") as advance:
            for _ in range(20):
                time.sleep(0.05)
                advance(1)
        terminal.flush()
        os.set_blocking(master, False)
        shown = b""
        try:
            while chunk := os.read(master, 65536):
                shown += chunk
        except (BlockingIOError, OSError):
            pass
    os.close(master)
    lines = shown.decode().split("\r")
    # 20 images at about 20 a second (fewer on a busy machine): 40 left take 2 s or more
    assert any(re.search(r"detecting .*\b20/60  00:00:\d\d  \d+\.\d images/s", line)
               for line in lines), lines[-3:]
