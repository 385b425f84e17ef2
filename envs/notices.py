"""Two third-party notices kept off the user's terminal, each removed at its source before the
first import of its package; any other output of those imports still shows.

MJX's optional Warp backend prints "Failed to import warp" and "Failed to import mujoco_warp" to
stdout when Warp is absent (it is not used here); gymnasium-robotics prints a notice about its
Adroit hand tasks' rewards to stderr on import (through ``farama_notifications``). Neither is
dropped at this module's import: the functions are called where MJX or gymnasium-robotics is
first imported.
"""

from __future__ import annotations

import contextlib
import io
import sys

_WARP_NOTICES = ("Failed to import warp:", "Failed to import mujoco_warp:")


def quiet_mjx() -> None:
    """Import ``mujoco.mjx`` with Warp's absence notices dropped. Call it before any import of
    MJX (or of something that imports it); a no-op once MJX is loaded."""
    if "mujoco.mjx" not in sys.modules:
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            import mujoco.mjx  # noqa: F401
        rest = [ln for ln in buf.getvalue().splitlines(keepends=True)
                if not ln.startswith(_WARP_NOTICES)]
        sys.stdout.write("".join(rest))


def quiet_gymnasium_robotics() -> None:
    """Drop gymnasium-robotics' Adroit notice from farama's table before ``gymnasium_robotics``
    is first imported. Idempotent; a no-op once it is loaded."""
    if "gymnasium_robotics" not in sys.modules:
        with contextlib.suppress(ImportError):
            from farama_notifications import notifications

            adroit = notifications.get("gymnasium_robotics", {})
            for version in [v for v, text in adroit.items() if text.startswith("Adroit")]:
                del adroit[version]
