"""Every ```python block of README.md runs as written and its own asserts hold."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

README = Path(__file__).resolve().parents[1] / "README.md"
BLOCKS = re.findall(r"```python\n(.*?)```", README.read_text(encoding="utf-8"), flags=re.S)


def test_readme_is_a_short_page_with_snippets():
    text = README.read_text(encoding="utf-8")
    assert len(text) <= 20_000
    assert len(BLOCKS) >= 5
    for link in re.findall(r"\]\(((?:benchmarks|docs)/[^)#]+)", text):
        assert (README.parent / link).is_file(), link  # every linked result and doc exists


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_snippet_runs(index, tmp_path, monkeypatch):
    code = BLOCKS[index]
    assert "assert " in code, "each snippet checks its own result"
    monkeypatch.chdir(tmp_path)  # logs (runs/...) go to a temporary folder
    dtype, threads = torch.get_default_dtype(), torch.get_num_threads()
    try:
        exec(compile(code, f"README.md snippet {index + 1}", "exec"), {"__name__": "__readme__"})
    finally:
        torch.set_default_dtype(dtype)
        torch.set_num_threads(threads)
