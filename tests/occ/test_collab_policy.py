"""Who may hand over control of a collaborative slave, and which slave a master drives:
occ.net.collab's Collaboration (the hand-over policy) and SlaveSelector, each alone, every case
answered with its whole text (issue 29: mutation testing of the hand-over path). The path
through a running slave (the desk, the streams' liveness check, the re-entry) is in
test_collab.py."""

from __future__ import annotations

from typing import Any

import pytest

from occ.net.collab import Collaboration, SlaveSelector
from occ.config import CollaborationConfig
from occ.errors import CommandError

MASTERS = [
    {"input": "mentor", "console": "mentor_desk"},
    {"input": "trainee", "console": "trainee_desk"},
    {"input": "fellow", "console": None},
]


def collab(**policy: Any) -> Collaboration:
    return Collaboration(CollaborationConfig(masters=MASTERS, **policy))


def refusal(co: Collaboration, interface: str, to: str) -> str:
    with pytest.raises(CommandError) as err:
        co.authorize(interface, to)
    return str(err.value)


@pytest.mark.req("SR-SEC-6")
def test_the_defaults_first_master_owns_every_master_may_grant_nobody_may_request() -> None:
    co = collab()
    assert co.owner == "mentor" and co.masters == ("mentor", "trainee", "fellow")
    assert co.code() == 0 and co.code("fellow") == 2
    assert co.console_of == {"mentor_desk": "mentor", "trainee_desk": "trainee"}
    assert co.authorize("mentor_desk", "trainee") == "mentor"  # the owner grants
    assert refusal(co, "trainee_desk", "trainee") == (
        "trainee may not take control itself (not in request): ask mentor or the supervisor "
        "to hand it over"
    )
    # the bedside (nobody's console) acts as the supervisor by default
    assert co.authorize("bedside", "fellow") == "operator on bedside"
    assert (co.handovers, co.refused, list(co.history)) == (0, 0, [])
    co2 = collab(owner="trainee")
    assert co2.owner == "trainee" and co2.code() == 1


@pytest.mark.req("SR-SEC-6")
def test_every_console_and_target_is_decided_by_the_policy() -> None:
    co = collab(
        owner="trainee", supervisor="mentor", request=["fellow"], grant=["mentor"], others="refuse"
    )
    # the supervisor's console: anyone, itself included, whoever has control
    for to in co.masters:
        assert co.authorize("mentor_desk", to) == "mentor (supervisor)"
    # the owner, not in grant, may not give control away, nor keep "giving" it to itself
    assert refusal(co, "trainee_desk", "fellow") == (
        "trainee has control but may not give it away (not in grant)"
    )
    assert refusal(co, "trainee_desk", "trainee") == (
        "trainee has control but may not give it away (not in grant)"
    )
    # a console speaks only for its own master
    assert refusal(co, "trainee_desk", "mentor") == (
        "trainee has control but may not give it away (not in grant)"
    )
    # nobody's console with others: refuse
    assert refusal(co, "bedside", "mentor") == (
        "operators on bedside may not hand over control (no master's console; "
        "collaboration.others is refuse)"
    )
    # an unknown master is named, with the nearest name
    assert refusal(co, "mentor_desk", "mentr") == (
        "master 'mentr' is not one of ['mentor', 'trainee', 'fellow'] (did you mean 'mentor'?)"
    )
    assert refusal(co, "mentor_desk", "zzz") == (
        "master 'zzz' is not one of ['mentor', 'trainee', 'fellow']"
    )


@pytest.mark.req("SR-SEC-6")
def test_request_lets_a_console_take_control_for_its_own_master_only() -> None:
    masters = [
        {"input": "mentor", "console": "mentor_desk"},
        {"input": "trainee", "console": "trainee_desk"},
        {"input": "fellow", "console": "fellow_desk"},
    ]
    co = Collaboration(
        CollaborationConfig(masters=masters, supervisor=None, request=["trainee"], grant=[])
    )
    assert co.may_grant == frozenset() and co.may_request == frozenset({"trainee"})
    assert co.authorize("trainee_desk", "trainee") == "trainee"
    assert refusal(co, "trainee_desk", "fellow") == (
        "trainee does not have control: only mentor may give it away"
    )
    assert refusal(co, "fellow_desk", "fellow") == (
        "fellow may not take control itself (not in request): ask mentor or the supervisor "
        "to hand it over"
    )
    assert refusal(co, "mentor_desk", "trainee") == (
        "mentor has control but may not give it away (not in grant)"
    )
    # grant None means every master; an explicit list only those
    assert collab(grant=None).may_grant == frozenset({"mentor", "trainee", "fellow"})


def test_switch_records_the_last_sixteen_hand_overs() -> None:
    co = collab()
    assert co.switch("trainee", "mentor", 1.0) == "mentor"
    assert co.owner == "trainee" and co.handovers == 1 and co.code() == 1
    for k in range(20):
        co.switch("mentor" if k % 2 else "fellow", "x", 2.0 + k)
    assert co.handovers == 21 and len(co.history) == 16
    assert co.history[0] == (6.0, "mentor", "fellow", "x")  # the oldest 5 forgotten
    co.refused = 3
    st = co.stats()
    assert st == {
        "owner": co.owner,
        "masters": ["mentor", "trainee", "fellow"],
        "supervisor": None,
        "handovers": 21,
        "refused": 3,
        "history": [{"t": round(t, 6), "from": a, "to": b, "by": by} for t, a, b, by in co.history],
    }
    co.switch("trainee", "mentor (supervisor)", 1.23456789)
    assert co.stats()["history"][-1] == {
        "t": 1.234568,
        "from": "mentor",
        "to": "trainee",
        "by": "mentor (supervisor)",
    }


def test_a_slave_selector_drives_one_slave_at_a_time() -> None:
    one = SlaveSelector([])
    assert one.selected is None and one.drives("anything")
    with pytest.raises(CommandError, match=r"^this master drives one slave: nothing to select$"):
        one.select("x")
    with pytest.raises(CommandError, match=r"^this master drives one slave: nothing to toggle$"):
        one.toggle()
    single = SlaveSelector(["left"])
    with pytest.raises(CommandError, match=r"^this master drives one slave: nothing to toggle$"):
        single.toggle()
    sel = SlaveSelector(["left", "right"])
    assert sel.selected == "left" and sel.drives("left") and not sel.drives("right")
    assert sel.stats() == {"slaves": ["left", "right"], "selected": "left", "switches": 0}
    assert sel.select("left") == "left already selected" and sel.switches == 0
    assert sel.select("right") == "slave left -> right" and sel.switches == 1
    assert sel.toggle() == "slave right -> left" and sel.switches == 2
    with pytest.raises(CommandError) as err:
        sel.select("rigth")
    assert str(err.value) == (
        "slave interface 'rigth' is not one of ['left', 'right'] (did you mean 'right'?)"
    )
    three = SlaveSelector(["a", "b", "c"], selected="c")
    assert three.selected == "c" and three.toggle() == "slave c -> a"
    with pytest.raises(ValueError) as verr:
        SlaveSelector(["a", "b"], selected="z")
    assert str(verr.value) == "selected slave 'z' is not one of ['a', 'b']"


def test_a_clutch_tap_toggles_and_a_long_press_does_not() -> None:
    sel = SlaveSelector(["left", "right"], tap_s=0.25)  # binary-exact times: "exactly" is exact
    assert sel.on_clutch(False, 0.0) is None  # a release without a press
    assert sel.on_clutch(True, 1.0) is None
    assert sel.on_clutch(False, 1.25) == "slave left -> right"  # exactly the tap: a tap
    assert sel.on_clutch(True, 2.0) is None
    assert sel.on_clutch(False, 2.2500001) is None and sel.selected == "right"
    assert sel.on_clutch(False, 2.4) is None  # the press was used up
    no_tap = SlaveSelector(["left", "right"])
    no_tap.on_clutch(True, 0.0)
    assert no_tap.on_clutch(False, 0.01) is None and no_tap.selected == "left"
    single = SlaveSelector(["left"], tap_s=0.25)
    single.on_clutch(True, 0.0)
    assert single.on_clutch(False, 0.1) is None
