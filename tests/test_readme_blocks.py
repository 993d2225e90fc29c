"""benchmarks/readme_blocks.py without running anything: how it reads a README's blocks, puts the
emulator's connection for the placeholders, takes the install out, and which check_docs claims it
checks against which README block (the runs: `python benchmarks/readme_blocks.py` in a fresh clone)."""
import importlib.util
import sys

from cli_run import ROOT

_spec = importlib.util.spec_from_file_location("readme_blocks", ROOT / "benchmarks" / "readme_blocks.py")
rb = sys.modules["readme_blocks"] = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(rb)

MD = """# title
text
```bash
torchblur emulator seed=1 &                  # prints {"serial": "/dev/pts/N", "frames": "tcp://127.0.0.1:PORT", ...}
torchblur identify --out runs/bench rig.kind=serial rig.port=/dev/pts/N rig.frames=tcp://127.0.0.1:PORT
torchblur identify --resume runs/bench rig.port=/dev/pts/M rig.frames=tcp://127.0.0.1:PORT2   # after a fault
```
```
plain text
```
```python
print(1)  # exit status 4
```
"""


def test_blocks_are_read_in_order_with_their_language_and_line():
    got = rb.blocks(MD)
    assert [(lang, line) for lang, _, line in got] == [("bash", 3), ("text", 8), ("python", 11)]
    assert got[0][1].count("\n") == 3 and got[1][1] == "plain text\n" and got[2][1] == "print(1)  # exit status 4\n"
    assert rb.expected_exit(got[2][1]) == {0, 4} and rb.expected_exit("x  # one line: y\n") == {0, 2}


def test_the_emulator_is_split_off_and_its_connection_put_for_every_placeholder():
    emulators, rest = rb.split_emulator(rb.blocks(MD)[0][1])
    assert emulators == ["torchblur emulator seed=1"]
    run = rb.substitute(rest, {"serial": "/dev/pts/7", "frames": "tcp://127.0.0.1:40123"})
    assert run.splitlines() == [
        "torchblur identify --out runs/bench rig.kind=serial rig.port=/dev/pts/7 rig.frames=tcp://127.0.0.1:40123",
        "torchblur identify --resume runs/bench rig.port=/dev/pts/7 rig.frames=tcp://127.0.0.1:40123   # after a fault"]
    # a placeholder-like path that is not one stays (/dev/pts/NN, PORTS)
    assert rb.substitute("/dev/pts/NN tcp://127.0.0.1:PORTS", {"serial": "s", "frames": "f"}) == "/dev/pts/NN tcp://127.0.0.1:PORTS"
    assert rb.block_commands(run) == [(("rig.frames=tcp://127.0.0.1:40123", "rig.kind=serial", "rig.port=/dev/pts/7"), "runs/bench")]


def test_skip_install_leaves_the_command():
    quick = "python3 -m venv .venv && . .venv/bin/activate && pip install -c constraints-cpu.txt -e . && torchblur identify --out runs/default\n"
    assert rb.skip_install(quick) == "torchblur identify --out runs/default\n"
    assert rb.skip_install("pip install -e '.[test]'\npython -m pytest\n") == "\npython -m pytest\n"


def test_every_example_claim_has_its_readme_block():
    """The claims on an example's printed lines are checked against the README block that runs it: the
    block's command and the claim's have the same keys (quotes, order and --out aside)."""
    readme = [keys for lang, code, _ in rb.blocks((ROOT / "README.md").read_text()) if lang == "bash"
              for keys, _ in rb.block_commands(code)]
    names = ("quick start: the default run's time", "the default run's mode with its stds", "verdict of the jitter example",
             "verdict of the fast-sweep example", "the slew-limit example's drive lines", "the size limit's estimate",
             "the DM run's verdict")
    claims = {c.name: c for c in rb.check_docs.CLAIMS}
    for name in names:
        assert rb.identify_keys(claims[name].cmd) in readme, name
    assert rb.identify_keys("torchblur identify --out x \"sweep.freq_hz=[1,2]\" a=1") == rb.identify_keys(
        ["python", "-m", "torchblur.cli", "identify", "a=1", "--out", "{out}", "sweep.freq_hz=[1,2]"])
