"""The plain text of ``occ-record why`` (occ/recording/why.py builds the explanation; this
writes it for a person): the trigger, each cause's chain, the holds of the last seconds, the
state transitions leading to the stop, and what the dump did not hold.

Every time is the daemon's clock as the dump holds it (``t=`` seconds), with the tick that took
it and how long before the trigger it was; numbers are written as the dump has them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

#: samples of a late stream written one by one (the JSON has them all)
SAMPLES_SHOWN = 8


def render(x: dict[str, Any]) -> str:
    """The explanation ``x`` (:func:`occ.recording.why.explain`) as text."""
    trig = x["trigger"]
    t0 = float(trig["t"])
    state = f", {trig['state']}" if trig.get("state") else ""
    utc = f" ({trig['utc']})" if trig.get("utc") else ""
    lines = [
        f"why: {x['robot']} at tick {trig['tick']}, t={t0:.6f} s{utc}{state}",
        f"dump: {x['dump']}",
    ]
    for i, chain in enumerate(x["chains"], start=1):
        lines += ["", f"cause {i}: {chain['cause']}: {chain['reason']}"]
        lines += ["  " + s for s in CHAINS.get(chain["kind"], _other)(chain, t0)]
        lines += [f"  not in the dump: {s}" for s in chain.get("lacks", [])]
    for h in x["holds"]:
        lines += ["", f"an earlier hold of the stream {h['stream']!r} ({h['ended']['kind']})"]
        lines += ["  " + s for s in _hold(h, t0)]
    if x.get("stream_events"):
        lines += ["", f"the loss monitors' events in the last {x['last_s']:g} s:"]
        lines += [
            f"  {_at(e, t0)}  {e['stream']}: {e['kind']}: {e['cause']}" for e in x["stream_events"]
        ]
    lines += ["", f"state transitions in the last {x['last_s']:g} s:"]
    lines += [
        f"  {_at(e, t0)}  {e['from']} -> {e['to']} ({e['event']}): {e['reason']}"
        for e in x["transitions"]
    ] or ["  none"]
    w = x["window"]
    sw = x.get("software") or {}
    lines += [
        "",
        f"window: {w.get('ticks')} ticks ({_num(w.get('seconds'), '.3f')} s) from tick "
        f"{w.get('first_tick')}; events whole from tick {w.get('events_whole_from_tick')}; "
        f"rows lost {w.get('rows_lost')}; occ {sw.get('occ', '?')} ({sw.get('build', '?')})",
    ]
    lines += [f"not in the dump: {s}" for s in x.get("lacks", [])]
    return "\n".join(lines) + "\n"


def _loss(c: dict[str, Any], t0: float) -> list[str]:
    out = [f"packet loss on the stream {c['stream']!r} (from {c['from']})"]
    good, proof = c.get("last_good") or {}, c.get("proved_by") or {}
    if good:
        out.append(f"last good  seq {good.get('seq')}{_taken(good, t0)}")
    if "lost" in c:
        nums = ", ".join(str(n) for n in c["lost"])
        more = f", ... ({c['count']} in all)" if c["count"] > len(c["lost"]) else ""
        rule = c.get("max_consecutive")
        why = (
            f"; more than safety.loss.max_consecutive = {rule} latch the stop"
            if rule is not None
            else ""
        )
        out.append(f"lost       seq {nums}{more} ({c['count']} in a row{why})")
    if proof:
        out.append(f"proved by  seq {proof.get('seq')}{_taken(proof, t0)}")
    j = c["judged"]
    since = j.get("since_last_good_ms")
    after = f", {since:.3f} ms after the last good sample" if isinstance(since, float) else ""
    out.append(f"judged     {_at(j, t0)}{after}: latched, policy {c.get('policy')}")
    return out


def _late(c: dict[str, Any], t0: float) -> list[str]:
    out = [f"the stream {c['stream']!r} came late (from {c['from']})"]
    if "last_good" in c:
        good = c["last_good"]
        seq = f"seq {good['seq']}" if good.get("seq") is not None else "a sample"
        out.append(f"last good  {seq}{_taken(good, t0)}")
    if "hold" in c:
        h = c["hold"]
        out.append(f"held       {_at(h, t0)}, {h['after_ms']:.1f} ms after it (the deadline)")
    if "samples" in c:
        out += _samples(c, "none accepted")
    latch = c["latched"]
    grace = c.get("grace_ms")
    limit = f"; safety.loss.grace_ms = {grace:g}" if isinstance(grace, int | float) else ""
    out.append(f"latched    {_at(latch, t0)}: {latch['cause']}{limit}; policy {c.get('policy')}")
    return out


def _hold(h: dict[str, Any], t0: float) -> list[str]:
    held, end = h["held"], h["ended"]
    good = h["last_good"]
    seq = f"seq {good['seq']}" if good.get("seq") is not None else "a sample"
    out = [
        f"last good  {seq}{_taken(good, t0)}",
        f"held       {_at(held, t0)}: {held['cause']}",
        *_samples(h, "the last one accepted" if end["kind"] == "resume" else "none accepted"),
    ]
    why = f": {end['cause']}" if end.get("cause") else ""
    out.append(f"{end['kind']:<10} {_at(end, t0)}{why}")
    return out


def _samples(c: dict[str, Any], taken: str) -> list[str]:
    """The samples that came after the last good one: when each was due and came, and for a
    stamped stream how much older than the freshest it was on arrival."""
    samples = c["samples"]
    if not samples:
        return ["after it   no sample came (the stream fell silent)"]
    fresh = c.get("freshest_age_ms")
    head = f"after it   {len(samples)} sample(s), {taken} (due every {c['period_ms']:g} ms"
    if fresh is not None:
        head += f"; the freshest before was {fresh:.1f} ms old on arrival"
    out = [head + "):"]
    shown = samples if len(samples) <= SAMPLES_SHOWN else samples[: SAMPLES_SHOWN - 1]
    out += ["  " + _late_sample(s) for s in shown]
    if len(shown) < len(samples):
        out.append(f"  ... {len(samples) - len(shown)} more, the last:")
        out.append("  " + _late_sample(samples[-1]))
    return out


def _late_sample(s: dict[str, Any]) -> str:
    text = (
        f"seq {s['seq']} came at t={s['t']:.6f} s (tick {s['tick']}), "
        f"{s['late_ms']:+.1f} ms against its due t={s['due']:.6f} s"
    )
    if "older_ms" in s:
        text += f"; {s['age_ms']:.1f} ms old on arrival: {s['older_ms']:+.1f} ms older"
    return text


def _drive(c: dict[str, Any], t0: float) -> list[str]:
    out = []
    for f in c["failures"]:
        out.append(f"drive {f['driver']!r}: {f['action']} failed: {f['cause']}")
        says = f": {f['rule_says']}" if f["rule_says"] else ""
        setting = f" (setting: {f['setting']})" if f["setting"] else ""
        out.append(f"rule       {f['rule']}{says}{setting}")
        for joint, readings in f["readings"].items():
            out.append(f"joint {joint}:")
            out += ["  " + _reading(r, t0) for r in readings]
    return out


def _reading(r: dict[str, Any], t0: float) -> str:
    parts = []
    if r.get("raw"):
        parts.append("raw " + " ".join(f"{k} {_num(v, '.9g')}" for k, v in r["raw"].items()))
    kept = r["kept"]
    parts.append("kept " + " ".join(f"{k} {_num(v, '.9g')}" for k, v in kept.items()))
    parts.append(f"setpoint {_num(r.get('setpoint'), '.9g')}")
    stamp, t = kept.get("stamp"), r.get("t")
    if isinstance(stamp, float) and isinstance(t, float) and stamp < t - 1e-9:
        parts.append(f"kept since t={stamp:.6f} s: this tick's reading was not taken")
    return f"{_at(r, t0)}: " + "; ".join(parts)


def _collision(c: dict[str, Any], t0: float) -> list[str]:
    if "verdict" not in c:
        return ["collision stop"]
    v = c["verdict"]
    # a clearance may be no number (JSON's "inf": a peer arm not seen, occ/kinematics/collision.py)
    out = [
        f"link {v['link']!r} near {v['near']!r}: clearance {_num(v['clearance_mm'], '.2f')} mm, "
        f"margin {_num(v['margin_mm'], '.2f')} mm (inside it by {_num(v['inside_by_mm'], '.2f')} "
        "mm)",
        f"verdict    seen by the loop {_at(v, t0)}" + (f": {v['text']}" if v.get("text") else ""),
    ]
    out += [
        f"other arm  {p['arm']}: clearance {_num(p['clearance_mm'], '.2f')} mm" for p in v["peers"]
    ]
    if c["before"]:
        out.append("verdicts before it:")
        out += [
            f"  {_at(b, t0)}  link {b['link']!r} near {b['near']!r}: clearance "
            f"{_num(b['clearance_mm'], '.2f')} mm"
            for b in c["before"]
        ]
    return out


def _request(c: dict[str, Any], t0: float) -> list[str]:
    if "interface" not in c:
        return [f"{c['command']} asked in tick {c['tick']}"]
    s = c.get("sender")
    who = (
        f" by {s.get('peer')} (role {s.get('role')}, signed {s.get('signed')})"
        if isinstance(s, dict)
        else ""
    )
    args = "".join(f' {k}="{v}"' for k, v in c["args"].items())
    out = [
        f"{c['command']} asked on the interface {c['interface']!r}{who}",
        f"request    {c['message']}{args}, taken {_at(c, t0)}",
    ]
    r = c.get("reply")
    if r:
        out.append(f"reply      {r['status']}: {r['message']}")
    return out


def _other(c: dict[str, Any], t0: float) -> list[str]:
    return ["no chain of its own in the dump: the reason above is what the robot said"]


CHAINS: dict[str, Callable[[dict[str, Any], float], list[str]]] = {
    "loss": _loss,
    "late": _late,
    "drive": _drive,
    "collision": _collision,
    "request": _request,
}


def _at(e: dict[str, Any], t0: float) -> str:
    """``t=... s (tick N, -x ms)``: a time of the dump and how long before the trigger."""
    t = e.get("t")
    if not isinstance(t, int | float):
        return f"in tick {e.get('tick')}"
    rel = (float(t) - t0) * 1e3
    when = "at the trigger" if abs(rel) < 1e-6 else f"{rel:+.3f} ms"
    return f"at t={float(t):.6f} s (tick {e.get('tick')}, {when})"


def _taken(s: dict[str, Any], t0: float) -> str:
    if s.get("tick") is None:
        return f", {_at(s, t0)} (not on the recording)"
    return f", taken by the loop {_at(s, t0)}"


def _num(v: Any, fmt: str) -> str:
    return format(v, fmt) if isinstance(v, int | float) else str(v)
