"""Keep third-party import notices that do not concern these tasks off the user's terminal.

Two notices reach every command otherwise: MJX's optional Warp backend prints "Failed to import
warp" and "Failed to import mujoco_warp" to stdout when Warp is absent (it is not used here), and
gymnasium-robotics prints a notice about its Adroit hand tasks' rewards to stderr on import
(through ``farama_notifications``). Each is removed at its source, before the first import of
its package; any other output of those imports still shows.
"""

from __future__ import annotations

import contextlib
import io
import sys

_WARP_NOTICES = ("Failed to import warp:", "Failed to import mujoco_warp:")


def quiet_imports() -> None:
    """Import ``mujoco.mjx`` with Warp's absence notices dropped, and drop gymnasium-robotics'
    Adroit notice before it is imported. Idempotent; a no-op once those modules are loaded."""
    if "mujoco.mjx" not in sys.modules:
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            import mujoco.mjx  # noqa: F401
        rest = [ln for ln in buf.getvalue().splitlines(keepends=True)
                if not ln.startswith(_WARP_NOTICES)]
        sys.stdout.write("".join(rest))
    if "gymnasium_robotics" not in sys.modules:
        with contextlib.suppress(ImportError):
            from farama_notifications import notifications

            adroit = notifications.get("gymnasium_robotics", {})
            for version in [v for v, text in adroit.items() if text.startswith("Adroit")]:
                del adroit[version]
