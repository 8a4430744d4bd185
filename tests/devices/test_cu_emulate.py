"""``omnid emulate control-unit --pty`` as a bench user runs it: a separate process on a pty."""

from __future__ import annotations

import asyncio
import subprocess
import sys

from omnid.cli import main
from omnid.devices import cu_codec as codec
from omnid.devices.control_unit import WheelCommand
from omnid.devices.transport import open_transport


def test_emulate_prints_pty_path_and_answers_commands(tmp_path):
    link = tmp_path / "ttyBENCH"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "omnid.cli",
            "emulate",
            "control-unit",
            "--pty",
            "--link",
            str(link),
            "--status-every-s",
            "0",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        path = proc.stdout.readline().strip()
        assert path == str(link)

        async def exchange():
            t = open_transport(path)
            # the unit obeys ENABLE only after a zero frame (protocol "Freshness")
            await t.write(codec.encode_command(WheelCommand.stop().to_frame(41, cycle=1)))
            await t.read_exactly(codec.REPLY_FRAME_LEN, 2.0)
            cmd = WheelCommand(0.2, 0.2, enable=True).to_frame(42, cycle=2)
            await t.write(codec.encode_command(cmd))
            rep = codec.decode_frame(await t.read_exactly(codec.REPLY_FRAME_LEN, 2.0))
            t.close()
            return rep

        rep = asyncio.run(exchange())
        assert isinstance(rep, codec.ReplyFrame) and rep.seq == 42 and rep.left_applied_pm == 200
    finally:
        proc.terminate()
        proc.wait(timeout=5)


def test_unknown_emulator_is_one_line_error(capsys):
    assert main(["emulate", "toaster"]) == 2
    err = capsys.readouterr().err
    assert "toaster" in err and "control-unit" in err and "Traceback" not in err
