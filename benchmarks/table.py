"""The one table every benchmark prints: rows {name, value, unit, target[, higher_is_better]}.

A row that misses its target is marked MISSED: rates (units per second, or ``higher_is_better``)
must reach the target; everything else must stay under it.
"""

from __future__ import annotations

from collections.abc import Sequence


def missed(row: dict) -> bool:
    """Whether ``row`` has a numeric target that its value does not meet."""
    target, value = row.get("target"), row["value"]
    if not (isinstance(target, (int, float)) and isinstance(value, (int, float))):
        return False
    higher_is_better = row.get("higher_is_better", str(row.get("unit", "")).endswith("/s"))
    return not (value >= target if higher_is_better else value <= target)


def print_rows(rows: Sequence[dict], areas: Sequence[str] | None = None) -> None:
    """Print ``rows`` as a table, with an area column when ``areas`` (one per row) is given."""
    width = max(len(r["name"]) for r in rows)
    area_head = f"{'area':14} " if areas is not None else ""
    print(f"{area_head}{'benchmark':{width}} {'value':>12} {'unit':10} {'target':>10}")
    for i, r in enumerate(rows):
        value = r["value"]
        shown = f"{value:12.4g}" if isinstance(value, (int, float)) else f"{value!s:>12}"
        target = "" if r.get("target") is None else f"{r['target']:g}"
        area = f"{areas[i]:14} " if areas is not None else ""
        flag = "  MISSED" if missed(r) else ""
        print(f"{area}{r['name']:{width}} {shown} {r.get('unit', ''):10} {target:>10}{flag}")
