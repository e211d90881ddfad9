"""The runtime's one error base.

Every refusal the crowd package raises is a CrowdError whose message is one line naming what was refused:
bad input, a file it cannot read, a GL context it cannot use. Each stage's own class (RenderError,
GltfImportError, ...) derives from it and from the built-in it always was (ValueError or RuntimeError), so
app/ catches CrowdError once, and a caller that caught the built-in still does.
"""

from __future__ import annotations


class CrowdError(Exception):
    """A refusal of the crowd package; str() is one line."""
