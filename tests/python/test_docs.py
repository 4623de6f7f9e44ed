"""The Python examples in README.md and docs/ORACLE.md run as written (from the repository
root, where their fixture paths point)."""

import os
import re

import pytest

from conftest import ROOT

BLOCKS = [
    (doc, i, code)
    for doc in ("README.md", "docs/ORACLE.md")
    for i, code in enumerate(re.findall(r"```python\n(.*?)```", (ROOT / doc).read_text(), re.S))
]


def test_the_docs_have_examples():
    assert {doc for doc, _, _ in BLOCKS} == {"README.md", "docs/ORACLE.md"}


@pytest.mark.parametrize("doc,index,code", BLOCKS, ids=[f"{d}[{i}]" for d, i, _ in BLOCKS])
def test_example_runs(doc, index, code, monkeypatch):
    monkeypatch.chdir(ROOT)
    exec(compile(code, f"{doc} python block {index}", "exec"), {"__name__": "docs_example"})
