"""Frames reach nodes in batches (Node.handle_batch): generations in one process (Router, the
in-process engine, NodeGroup), every pending frame of a bus in a node process."""
from __future__ import annotations

from pathlib import Path

import can
import pytest

from canbrake.nodes.base import Node, exact_filter, frame
from canbrake.nodes.driver import NodeCrash, run_inprocess
from canbrake.nodes.group import NodeGroup, Router


class Talker(Node):
    """Sends ``n`` frames 0x100.. at start; finishes when it hears 0x300."""

    def __init__(self, name: str, n: int) -> None:
        self.name, self.n, self.batches = name, n, []

    def filters(self) -> list[dict]:
        return [exact_filter(0x200), exact_filter(0x300)]

    def start(self, now: float) -> list[can.Message]:
        return [frame(0x100 + i, bytes([i])) for i in range(self.n)]

    def handle(self, msg: can.Message, now: float) -> list[can.Message]:
        self.batches.append([msg.arbitration_id])
        if msg.arbitration_id == 0x300:
            self.finished = True
        return []

    def handle_batch(self, msgs: list[can.Message], now: float) -> list[can.Message]:
        self.batches.append([m.arbitration_id for m in msgs])
        if any(m.arbitration_id == 0x300 for m in msgs):
            self.finished = True
        return []


class Echo(Node):
    """Answers every 0x1xx frame with 0x200 (its byte); then 0x300 once it has seen ``n``."""

    def __init__(self, n: int) -> None:
        self.name, self.n, self.calls, self.seen = "echo", n, 0, 0
        self.time_master = True

    def handle(self, msg: can.Message, now: float) -> list[can.Message]:
        raise AssertionError("the engines call handle_batch")

    def handle_batch(self, msgs: list[can.Message], now: float) -> list[can.Message]:
        self.calls += 1
        out = [frame(0x200, bytes(m.data)) for m in msgs if 0x100 <= m.arbitration_id < 0x200]
        self.seen += len(out)
        if self.seen >= self.n and not self.finished:
            out.append(frame(0x300, b""))
            self.finished = True
        return out


def test_generations_one_call_per_node_and_own_frames_left_out() -> None:
    a, b = Talker("a", 3), Talker("b", 2)
    echo = Echo(5)
    moved = run_inprocess([a, b, echo])
    assert moved == 5 + 5 + 1
    assert echo.calls == 1  # the five start frames are one generation: one call
    # each talker: the five answers in one batch (bus order: a's frames first), then the end
    assert a.batches == [[0x200] * 5 + [0x300]] and b.batches == a.batches
    assert all(x.finished for x in (a, b, echo))


def test_default_handle_batch_stops_at_the_frame_that_finished_the_node() -> None:
    class Plain(Talker):
        handle_batch = Node.handle_batch

    p = Plain("p", 0)
    p.handle_batch([frame(0x200, b"\x01"), frame(0x300, b""), frame(0x200, b"\x02")], 0.0)
    assert p.batches == [[0x200], [0x300]]  # the frame after the end is not handled


def test_router_routes_by_filter_and_skips_the_sender() -> None:
    a, b = Talker("a", 0), Talker("b", 0)
    everyone = Echo(99)
    r = Router([a, b, everyone])
    gen = [(0, frame(0x200, b"")), (2, frame(0x300, b"")), (1, frame(0x7FF, b""))]
    inbox = r.inboxes(gen)
    assert [m.arbitration_id for m in inbox[0]] == [0x300]           # not its own 0x200
    assert [m.arbitration_id for m in inbox[1]] == [0x200, 0x300]    # 0x7FF: not in its filters
    assert [m.arbitration_id for m in inbox[2]] == [0x200, 0x7FF]    # no filter: all but its own


def test_group_delivers_members_frames_to_each_other_in_generations() -> None:
    a, echo = Talker("a", 4), Echo(4)
    g = NodeGroup([a, echo])
    out = g.start(0.0)
    assert [m.arbitration_id for m in out] == [0x100, 0x101, 0x102, 0x103] + [0x200] * 4 + [0x300]
    assert echo.calls == 1 and a.batches == [[0x200] * 4 + [0x300]]
    assert g.finished


def test_a_crash_in_a_batch_names_the_node() -> None:
    class Bad(Echo):
        def handle_batch(self, msgs: list[can.Message], now: float) -> list[can.Message]:
            raise ValueError("boom")

    bad = Bad(1)
    bad.name = "ecu7"
    with pytest.raises(NodeCrash, match="ecu7: ValueError: boom"):
        run_inprocess([Talker("a", 1), bad])


def test_chen_case1_each_ecu_is_called_once_per_phase(tmp_path: Path) -> None:
    """In process, an ECU of Chen case 1 takes its period's frames in two calls (the plant's
    tick frames; its peers' states), the plant one (the commands), the recorder three."""
    from canbrake.nodes.ecu import EcuNode
    from canbrake.nodes.plant import PlantNode
    from canbrake.nodes.recorder import RecorderNode
    from canbrake.run import run_scenario
    from canbrake.scenario import load_scenario

    calls: dict[str, int] = {}
    # the Router calls each node's batch handler (Node.batch_handler: handle_batch, or the ECU's
    # compiled equivalent): count the calls of the handler each node gives
    originals = {cls: cls.batch_handler for cls in (EcuNode, PlantNode, RecorderNode)}

    def counting(cls):  # type: ignore[no-untyped-def]
        def wrapper(self):  # type: ignore[no-untyped-def]
            handler = originals[cls](self)

            def counted(msgs, now):  # type: ignore[no-untyped-def]
                calls[cls.__name__] = calls.get(cls.__name__, 0) + 1
                return handler(msgs, now)
            return counted
        return wrapper

    scn = load_scenario(Path(__file__).parents[1] / "scenarios" / "chen2023_case1_fine_rail.yaml",
                        overrides={"duration_s": 0.05})
    try:
        for cls in originals:
            cls.batch_handler = counting(cls)  # type: ignore[method-assign]
        s = run_scenario(scn, tmp_path, backend="inprocess", plots=False)
    finally:
        for cls, fn in originals.items():
            cls.batch_handler = fn  # type: ignore[method-assign]
    ticks = s["ticks"]
    assert ticks == 50
    assert calls["EcuNode"] <= 6 * 2 * (ticks + 1)
    assert calls["PlantNode"] <= ticks + 1
    assert calls["RecorderNode"] <= 3 * (ticks + 1)
