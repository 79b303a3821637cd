"""The stress test's report: ``report.md`` and one self-contained ``report.html``.

Both show the same tables, built once (:func:`tables`) from ``summary.json``'s dict: the
failure rates with their 95% intervals, the time to collision, the collision types, the
ego collision rate per road family and the failures, worst first; then the GIFs of the
worst failures (the attacker haloed red with its track, the escape the search found, the
*witness*, green). The Markdown links the GIFs (``gifs/``); the HTML page embeds them
(base64), so that it can be sent as one file.
"""

from __future__ import annotations

import base64
import html
import math
import shlex
from pathlib import Path
from typing import Any

from policies.stress.replay import describe_failure
from policies.stress.summary import counted, headline
from riskflow_env.atomic_files import write_text

Table = tuple[str, list[str], list[list[str]]]  # title, header, rows

RATES = (
    ("ego_collision_rate", "ego collision rate (episodes)", "%"),
    ("avoidable_failure_rate", "avoidable-failure rate (episodes): the headline", "%"),
    ("avoidable_share", "ego collisions shown avoidable", "%"),
    ("standing_strike_share", "ego collisions with the ego standing", "%"),
    ("plausible_share", "attacker within the human p99 bounds", "%"),
    ("wreck_share", "ego collisions with a vehicle already in a collision", "%"),
    ("non_ego_contact_share", "non-ego vehicles in a collision without the ego", "%"),
    ("ego_offroad_rate", "ego off the road (episodes)", "%"),
    ("attackers_at_impact", "guided vehicles within 5 m of the ego at impact", ""),
    ("progress", "distance the ego drove [m]", ""),
    ("ego_collisions_per_km", "episodes with an ego collision per km driven (n: them)", ""),
    ("attacked_rate", "episodes with a guided vehicle (target ego: an attacker)", "%"),
    ("slow_ego_share", "share of the ego's steps below 2 m/s (no new attack; n: episodes)", "%"),
    ("time_to_first_ego_collision", "time to the first ego collision [s]", ""),
    ("attack_to_impact", "time from the attack's start to the impact [s]", ""),
)
MAX_FAILURE_ROWS = 50


def fmt(entry: dict[str, Any], unit: str = "") -> tuple[str, str]:
    """(value, "[low, high]") of a summary entry, as percent with ``unit == "%"``."""
    value, low, high = entry.get("value"), entry.get("low"), entry.get("high")
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a", ""
    if unit == "%":
        text = f"{100 * value:.1f}%"
        interval = "" if low is None else f"[{100 * low:.1f}, {100 * high:.1f}]"
    else:
        text = f"{value:.2f}"
        interval = "" if low is None else f"[{low:.2f}, {high:.2f}]"
    return text, interval


def tables(summary: dict[str, Any]) -> list[Table]:
    """The report's tables (module docstring)."""
    rates = [
        [label, *fmt(summary[key], unit), str(summary[key]["n"])]
        for key, label, unit in RATES
        if key in summary
    ]
    types = [
        [kind, str(row["collisions"]), str(row["avoidable"])]
        for kind, row in summary["types"].items()
    ]
    families = [
        [family, *fmt(entry, "%"), str(entry["n"])] for family, entry in summary["families"].items()
    ]
    failures = [
        [
            episode["scene"],
            str(episode["seed"]),
            f"{f['time']:.1f}",
            f["type"] + (", a wreck" if f.get("wreck") else ""),
            f["attacker"],
            f"{f['relative_speed']:.1f}",
            f"{f['ego_speed']:.1f}",
            "yes" if f["avoidable"] else "not shown",
            "yes" if f["plausible"] else "no",
            episode["replay"] or "",
        ]
        for episode in summary["per_episode"]
        for f in episode["failures"]
    ]
    failures.sort(key=lambda row: (row[7] != "yes", -float(row[5])))
    return [
        ("Failure rates (95% intervals: Wilson for rates, bootstrap for means)",
         ["", "value", "95% interval", "n"], rates),
        ("Ego collisions by type", ["type", "collisions", "avoidable"], types),
        ("Ego collision rate by road family", ["family", "rate", "95% interval", "episodes"],
         families),
        (f"Failures, worst first (at most {MAX_FAILURE_ROWS})",
         ["scene", "seed", "t [s]", "type", "attacker", "impact [m/s]", "ego [m/s]",
          "avoidable", "plausible attacker", "replay file"], failures[:MAX_FAILURE_ROWS]),
    ]  # fmt: skip


def title(summary: dict[str, Any]) -> tuple[str, str]:
    """(title, the options in one line)."""
    o = summary["options"]
    seeds = ", ".join(str(s) for s in o["seeds"])
    stopped = summary.get("interrupted")
    cause = stopped.get("cause", "interrupted") if stopped else ""
    done = f" ({cause}: {stopped['episodes']} of {stopped['planned']})" if stopped else ""
    return (
        f"Stress test of {summary['planner']}",
        f"{counted(summary['episodes'], 'episode')}{done}: {counted(o['scenes'], 'scene')} x seeds "
        f"{seeds}; RiskFlow "
        f"K={o['k']}, target {o['target']}, re-plan every {o['planning_interval']} s, "
        f"{o['steps']} steps of 0.1 s",
    )


def replay_command(row: dict[str, Any], planner: str, folder: Path) -> str:
    """The command that replays ``row``'s failure, to run where the stress test ran (the
    replay file under the output ``folder`` as it was given, like the ``planner`` spec)."""
    replay = shlex.quote(str(folder / row["replay"]))
    return f"riskflow-stress replay {replay} --planner {shlex.quote(planner)}"


def markdown(summary: dict[str, Any], gifs: list[dict[str, Any]], folder: Path) -> str:
    """``report.md``."""
    heading, options = title(summary)
    lines = [f"# {heading}", "", options, "", f"**{headline(summary)}**", ""]
    for caption, header, rows in tables(summary):
        lines += [f"## {caption}", "", "| " + " | ".join(header) + " |"]
        lines += ["|" + "---|" * len(header)]
        lines += ["| " + " | ".join(row) + " |" for row in rows] or ["| (none) |"]
        lines.append("")
    if gifs:
        lines += ["## Worst failures", ""]
    for row in gifs:
        lines += [f"### {row['scene']}, seed {row['seed']}", ""]
        lines += [f"- {describe_failure(f)}" for f in row["failures"]]
        lines += ["", _reproduced(row), "", f"![{row['scene']}]({row['gif']})", ""]
        lines += ["```", replay_command(row, summary["planner"], folder), "```", ""]
    return "\n".join(lines)


def page(summary: dict[str, Any], gifs: list[dict[str, Any]], folder: Path) -> str:
    """``report.html``: the tables and the GIFs embedded."""
    heading, options = title(summary)
    esc = html.escape
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'>",
        f"<title>{esc(heading)}</title><style>{STYLE}</style></head><body>",
        f"<h1>{esc(heading)}</h1><p>{esc(options)}</p>",
        f"<p class='headline'>{esc(headline(summary))}</p>",
    ]
    for caption, header, rows in tables(summary):
        parts.append(f"<h2>{esc(caption)}</h2><table><tr>")
        parts += [f"<th>{esc(cell)}</th>" for cell in header]
        parts.append("</tr>")
        for row in rows or [["(none)"]]:
            parts.append("<tr>" + "".join(f"<td>{esc(cell)}</td>" for cell in row) + "</tr>")
        parts.append("</table>")
    if gifs:
        parts.append("<h2>Worst failures</h2>")
    for row in gifs:
        data = base64.b64encode((folder / row["gif"]).read_bytes()).decode("ascii")
        items = "".join(f"<li>{esc(describe_failure(f))}</li>" for f in row["failures"])
        parts += [
            f"<h3>{esc(row['scene'])}, seed {row['seed']}</h3><ul>{items}</ul>",
            f"<p>{esc(_reproduced(row))}</p>",
            f"<img alt='{esc(row['scene'])}' src='data:image/gif;base64,{data}'>",
            f"<pre>{esc(replay_command(row, summary['planner'], folder))}</pre>",
        ]
    parts.append("</body></html>")
    return "\n".join(parts)


def _reproduced(row: dict[str, Any]) -> str:
    if row["reproduced"]:
        return "Re-run for this picture: the same episode, bit for bit."
    return (
        "Warning: re-run for this picture, the episode came out different: the planner is "
        "not deterministic, or its reset(view) keeps state from earlier episodes."
    )


def write_reports(folder: Path, summary: dict[str, Any], gifs: list[dict[str, Any]]) -> None:
    """Write ``report.md`` and ``report.html`` into ``folder``."""
    write_text(folder / "report.md", markdown(summary, gifs, folder))
    write_text(folder / "report.html", page(summary, gifs, folder))


STYLE = (
    "body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}"
    "table{border-collapse:collapse;margin-bottom:1em}"
    "td,th{border:1px solid #ccc;padding:3px 8px;text-align:left;font-size:90%}"
    "th{background:#eee}.headline{font-weight:bold;font-size:110%}"
    "pre{background:#f4f4f4;padding:6px}"
)

__all__ = ["markdown", "page", "tables", "write_reports"]
