"""The API's documented limits (docs/api.md, "Limits"): what a request may hold at most.

The body size itself is Django's DATA_UPLOAD_MAX_MEMORY_SIZE (settings.py), which the HTTP
layer (lifecycle_site/serve.py) enforces too, before a body is read."""
from __future__ import annotations

from django.conf import settings
from django.utils.translation import gettext as _

# Lists and objects nested deeper than this in a JSON body are refused (no endpoint needs more
# than 3: a parameter holding an array, inside the body).
MAX_DEPTH = 32
# Digits of one integer in a JSON body: Python's own limit for turning text into an int.
MAX_DIGITS = 4300
# Names in one PATCH .../parameters: each is sent to the node and written to the audit log.
MAX_PARAMETERS = 200
# Node names in "nodes" of one group operation.
MAX_NODES = 200


def body_limit() -> int:
    return settings.DATA_UPLOAD_MAX_MEMORY_SIZE


def size_text(size: int) -> str:
    """1048576 -> "1 MiB", 2000 -> "2,000 bytes"."""
    if size % (1024 * 1024) == 0:
        return f"{size // (1024 * 1024)} MiB"
    if size % 1024 == 0:
        return f"{size // 1024} KiB"
    return _("%(size)s bytes") % {"size": f"{size:,}"}

