#!/usr/bin/env bash
# Regenerate the files derived from the steps' settings dataclasses; tests/test_settings.py fails
# while they are stale:
#   workflow/schemas/config.schema.yaml   python -m seathru.settings schema
#   config/README.md (between the settings markers)   python -m seathru.settings docs
# Usage: bash .ci/generate.sh   (PYTHON=... to use another interpreter than .venv/bin/python)
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-.venv/bin/python}

schema=$("$PYTHON" -m seathru.settings schema)
docs=$("$PYTHON" -m seathru.settings docs)
printf '%s\n' "$schema" > workflow/schemas/config.schema.yaml
DOCS="$docs" "$PYTHON" - <<'PY'
import os
import re
from pathlib import Path

readme = Path("config/README.md")
text = readme.read_text()
pattern = re.compile(r"(<!-- settings:begin[^\n]*-->\n).*?(<!-- settings:end -->)", re.S)
if not pattern.search(text):
    raise SystemExit(f"{readme}: the settings markers are missing")
text = pattern.sub(lambda m: m.group(1) + "\n" + os.environ["DOCS"].strip("\n") + "\n\n"
                   + m.group(2), text, count=1)
readme.write_text(text)
PY
echo "regenerated workflow/schemas/config.schema.yaml and config/README.md"
