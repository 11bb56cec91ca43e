"""The services' output log (``services.common.OutputLog``): what a restarted service publishes
again. Reference: the log's contract in its docstring and docs/services.md ("Restarts")."""

from __future__ import annotations

from services.common import OutputLog


def write(path, lines: list[str]) -> None:
    path.write_text("".join(line + "\n" for line in lines))


def test_only_the_outputs_logged_just_before_the_stop_are_at_risk(tmp_path):
    path = tmp_path / "oos.published"
    write(
        path,
        [
            "a.open\tdivert\t0\t1000.000000",
            "a\talert\t0\t1100.000000",
            "a.final\tdivert\t1\t1100.500000",  # 1.5 s before the last line
            "b.open\tdivert\t2\t1102.000000",
        ],
    )
    log = OutputLog(path, at_risk_s=2.0)
    assert {"a.open", "a", "a.final", "b.open"} <= log.done
    assert log.at_risk == {"a", "a.final", "b.open"}
    assert log.take_at_risk("a.final") == ("divert", 1)
    assert log.take_at_risk("a.final") is None  # once
    assert log.take_at_risk("a.open") is None  # long sent
    assert (log.next_seq("divert"), log.next_seq("alert"), log.next_seq("x")) == (3, 1, 0)
    log.close()


def test_the_earlier_format_and_a_torn_line_are_read(tmp_path):
    path = tmp_path / "oos.published"
    path.write_text("a.open\na\na.fin")  # ids alone; the last line torn by a crash
    log = OutputLog(path)
    assert log.done == {"a.open", "a"} and "a.fin" not in log
    assert log.at_risk == set() and log.next_seq("divert") == 0
    log.add("a.final", "divert", 7)  # then the process dies: no closing line
    again = OutputLog(path)
    assert "a.final" in again and again.positions["a.final"] == ("divert", 7)
    assert again.at_risk == {"a.final"}
    again.close()
    assert OutputLog(path).at_risk == set()  # closed after a clean stop: nothing at risk
