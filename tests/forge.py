"""Forging a run directory's stage record, for tests of what a run checks beyond it."""

import hashlib
import json
from pathlib import Path

from nlyap_opt.workflow.pipeline import _hash


def forge_stage_file(out: Path, stage: str, name: str) -> None:
    """Record file ``name``'s present bytes as the ones stage ``stage`` wrote, in
    ``out/stages.json``, sealed as the run seals it: what someone who edits both the file
    and its record (not by accident) leaves behind. The run must still check the file's
    content itself."""
    path = Path(out) / "stages.json"
    st = json.loads(path.read_text())
    rec = st[stage]
    rec["files"][name] = hashlib.sha256((Path(out) / name).read_bytes()).hexdigest()
    rec["seal"] = _hash([rec["key"], rec["files"]])
    path.write_text(json.dumps(st))
