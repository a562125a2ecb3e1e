"""What native libraries (Warp's start-up, USD's diagnostics) write straight to file descriptor 2.

Such text bypasses ``sys.stderr`` and would break the one-line answer of a user error, so the code
that triggers it runs inside :func:`held_stderr`, which collects it for the caller to turn into a
line of the project's own, or to drop.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile


@contextlib.contextmanager
def held_stderr():
    """Point descriptor 2 at a temporary file for the block; yields a list that receives the text
    written there (decoded, one string) when the block ends."""
    if sys.stderr is not None:
        sys.stderr.flush()
    saved = os.dup(2)
    held_text = []
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        try:
            yield held_text
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            held.seek(0)
            held_text.append(held.read().decode("utf-8", "replace"))
