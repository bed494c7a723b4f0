"""Rewrite the configuration reference's table (docs/reference/config.md) from SACConfig (run by `make docs`)."""

import re
from pathlib import Path

from softac.config.sac_config import SACConfig

readme = Path(__file__).resolve().parent.parent / "docs" / "reference" / "config.md"
text = readme.read_text()
table = f"<!-- config-table:start -->\n{SACConfig.markdown_table()}\n<!-- config-table:end -->"
readme.write_text(re.sub(r"<!-- config-table:start -->.*?<!-- config-table:end -->", lambda _: table, text, flags=re.S))
print(f"wrote the config table into {readme}")
