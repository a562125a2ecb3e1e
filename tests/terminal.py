"""Run a process with its standard error on a pseudo-terminal, as a user's shell would.

``softsim`` draws progress bars only on a terminal, and a closed terminal (SIGHUP, then ``EIO`` on
every write) can only be shown with one: :class:`TerminalRun` gives the process a pty as stderr
(and stdout, with ``stdout=True``), optionally as its controlling terminal, and reads what it
writes there continuously. :meth:`TerminalRun.hang_up` closes the terminal's master side: the
kernel then sends SIGHUP to the process (when the pty is its controlling terminal) and its later
writes fail, as when a terminal window is closed.
"""

from __future__ import annotations

import fcntl
import os
import pty
import select
import struct
import subprocess
import termios
import threading


class TerminalRun:
    def __init__(self, args, cwd, env=None, stdout=False, controlling=False, columns=200):
        master, slave = pty.openpty()
        # A real terminal's size, so that progress bars are drawn in full (a new pty reports 0 x 0).
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 50, columns, 0, 0))

        def make_controlling():
            fcntl.ioctl(2, termios.TIOCSCTTY, 0)

        self.proc = subprocess.Popen(
            args, cwd=cwd, env=env, stdin=subprocess.DEVNULL, stdout=slave if stdout else subprocess.DEVNULL,
            stderr=slave, start_new_session=controlling, preexec_fn=make_controlling if controlling else None,
        )
        os.close(slave)
        self.master = master
        self.out = b""
        self._stop = False
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self):
        # select with a timeout rather than a blocking read: a read in progress would keep the
        # master open through hang_up's close (the kernel releases a file when no call uses it).
        while not self._stop:
            if not select.select([self.master], [], [], 0.05)[0]:
                continue
            try:
                chunk = os.read(self.master, 4096)
            except OSError:  # EIO: every slave descriptor is closed
                return
            if not chunk:
                return
            self.out += chunk

    @property
    def text(self) -> str:
        return self.out.decode(errors="replace")

    def hang_up(self):
        """Close the terminal (its master side), as closing a terminal window does."""
        self._stop = True
        self._reader.join()
        master, self.master = self.master, -1
        os.close(master)

    def finish(self, timeout=60) -> int:
        code = self.proc.wait(timeout=timeout)
        self._reader.join(timeout=5)
        if self.master >= 0:
            os.close(self.master)
            self.master = -1
        return code
