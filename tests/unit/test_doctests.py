"""The examples in the docstrings of every module run and hold."""

from __future__ import annotations

import doctest
import importlib
import pkgutil

import pytest

import messages
import services
import sim


def _modules() -> list[str]:
    names = []
    for pkg in (messages, sim, services):
        for info in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
            if not info.name.endswith("__main__"):
                names.append(info.name)
    return sorted(names)


@pytest.mark.parametrize("name", _modules())
def test_doctests(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.failed == 0
