"""docs/protocol.md names what an outside client needs: the reply of every command. (Every configuration setting
is in the generated reference, docs/reference/configuration.md: tests/test_docs.py.)"""

from __future__ import annotations

import re
from pathlib import Path
from typing import get_args

from ddvs_service.protocol.control import Command, Counters

DOC = Path(__file__).resolve().parents[1] / "docs" / "protocol.md"


def test_protocol_doc_gives_each_commands_reply_data() -> None:
    text = DOC.read_text()
    section = text.split("**Reply data**", 1)
    assert len(section) == 2, "docs/protocol.md has no 'Reply data' table"
    ops = get_args(Command.model_fields["op"].annotation)
    rows = {m.group(1) for m in re.finditer(r"^\| `([a-z_]+)`[^|]*\|", section[1], re.MULTILINE)}
    assert set(ops) <= rows, f"no reply data row for {sorted(set(ops) - rows)}"
    assert all(f"`{name}`" in text for name in Counters.model_fields)
