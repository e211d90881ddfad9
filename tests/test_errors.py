"""Every refusal of the runtime is one CrowdError (crowd.errors), which app/ catches once."""

import importlib
import inspect
import pkgutil

import crowd
from crowd.errors import CrowdError

INTERNAL = {"BlockFormatRefused"}  # caught inside crowd.draw.materials, which falls back to another format


def test_every_error_class_of_the_runtime_is_a_crowd_error():
    found = {}
    for info in pkgutil.walk_packages(crowd.__path__, "crowd."):
        module = importlib.import_module(info.name)
        for name, cls in inspect.getmembers(module, inspect.isclass):
            if cls.__module__ == info.name and issubclass(cls, Exception) and cls.__name__ not in INTERNAL:
                found[f"{info.name}.{name}"] = cls
    assert len(found) >= 25, sorted(found)
    outside = sorted(name for name, cls in found.items() if not issubclass(cls, CrowdError))
    assert not outside, outside
    # Each keeps the built-in it always was, so a caller catching that still catches it.
    assert all(issubclass(cls, (ValueError, RuntimeError)) for name, cls in found.items() if cls is not CrowdError)
