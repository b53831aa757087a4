"""The examples in the docstrings of hapticloud.core run and give what they show."""

from __future__ import annotations

import doctest
import importlib
import pkgutil

import hapticloud.core as core
import pytest

MODULES = sorted(m.name for m in pkgutil.walk_packages(core.__path__, "hapticloud.core."))


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name: str) -> None:
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.failed == 0
