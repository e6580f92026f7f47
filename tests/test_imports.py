"""`import mbmon` and the pure layers must not pull in scapy or pyserial (DESIGN rule 8)."""

import subprocess
import sys
from pathlib import Path

import pytest

MODULES = [
    "mbmon",
    "mbmon.model",
    "mbmon.format",
    "mbmon.pipeline",
    "mbmon.cli",
    "mbmon.protocol.pdu",
    "mbmon.protocol.mbap",
    "mbmon.protocol.rtu",
    "mbmon.protocol.pairing",
    "mbmon.semantics.annotate",
    "mbmon.sources.pcapfile",
]


@pytest.mark.parametrize("module", MODULES)
def test_no_heavy_imports(module: str) -> None:
    code = (
        f"import sys, {module}; "
        "bad = [m for m in ('scapy', 'serial', 'pymodbus', 'textual') if m in sys.modules]; "
        "print(','.join(bad))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"{module} imports {out.stdout.strip()}"


@pytest.mark.parametrize(
    "module",
    [
        "mbmon.monitor",
        "mbmon.monitor.feed",
        "mbmon.commands.replay",
        "mbmon.commands.export",
        "mbmon.commands.info",
    ],
)
def test_the_monitor_imports_textual_only_when_a_screen_runs(module: str) -> None:
    code = f"import sys, {module}; print('textual' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_mbmon_read_does_not_import_textual() -> None:
    """``mbmon read`` (and every plain-line run) never loads the screen's toolkit."""
    capture = Path(__file__).resolve().parents[1] / "captures" / "hrss_ptp.pcap"
    if not capture.exists():
        pytest.skip("captures/hrss_ptp.pcap absent")
    code = (
        "import sys, io, contextlib\n"
        "from mbmon.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        f"    status = main(['read', {str(capture)!r}])\n"
        "print(status, 'textual' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["0", "False"], out.stdout + out.stderr


IO_MODULES = [
    "mbmon.io.replay",
    "mbmon.io.mcap",
    "mbmon.io.mcap.reader",
    "mbmon.io.mcap.layout",
    "mbmon.io.mcap.writer",
    "mbmon.io.mcap.reader",
    "mbmon.sinks.mcap",
]


@pytest.mark.parametrize("module", IO_MODULES)
def test_io_does_not_import_the_cli(module: str) -> None:
    """Dependencies point down: the log modules never pull in the command line."""
    code = (
        f"import sys, {module}; "
        "bad = [m for m in ('mbmon.cli', 'mbmon.commands') if m in sys.modules]; "
        "print(','.join(bad))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"{module} imports {out.stdout.strip()}"


def test_the_mcap_reader_does_not_import_the_writer() -> None:
    code = (
        "import sys, mbmon.io.mcap.reader; "
        "print(','.join(m for m in ('mbmon.io.mcap.writer', 'mbmon.io.mcap.layout', "
        "'mbmon.sinks.mcap') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_no_import_cycles_in_mbmon() -> None:
    """Dependencies point down: no module of mbmon reaches itself through its
    imports, lazy ones inside functions included."""
    import ast

    root = Path(__file__).resolve().parents[1] / "mbmon"
    modules: dict[str, Path] = {}
    for path in root.rglob("*.py"):
        name = ".".join(path.relative_to(root.parent).with_suffix("").parts)
        modules[name.removesuffix(".__init__")] = path
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        found: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text("utf-8"))):
            if isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join([*parts, base] if base else parts)
                found |= {base} | {f"{base}.{alias.name}" for alias in node.names}
            elif isinstance(node, ast.Import):
                found |= {alias.name for alias in node.names}
        graph[name] = {
            m
            for m in found
            if m in modules
            and m != name
            and not m.startswith(name + ".")
            and not name.startswith(m + ".")
        }

    def reach(start: str) -> set[str]:
        seen: set[str] = set()
        todo = [start]
        while todo:
            for nxt in graph[todo.pop()]:
                if nxt not in seen:
                    seen.add(nxt)
                    todo.append(nxt)
        return seen

    cycles = sorted({tuple(sorted((a, b))) for a in graph for b in graph[a] if a in reach(b)})
    assert cycles == []


#: What the analysis features need only when asked: port detection's module (the
#: dissector imports it only when detection is on), and the heavy libraries of
#: the report and parquet outputs.
OPTIONAL = ("mbmon.analysis.detect", "pyarrow", "matplotlib", "duckdb")


def test_the_report_imports_matplotlib_only_for_pictures() -> None:
    """``mbmon report`` without -o/--png prints tables: no plotting library is loaded."""
    code = (
        "import sys; from mbmon.analysis.report import analyse, text_tables; "
        "text_tables(analyse([])); print('matplotlib' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


@pytest.mark.parametrize(
    "module",
    [
        "mbmon",
        "mbmon.cli",
        "mbmon.sources.pcapfile",
        "mbmon.sources.dissect",
        "mbmon.commands.report",
        "mbmon.analysis.report",
        "mbmon.analysis.trigger",
        "mbmon.analysis.rotate",
        "mbmon.sinks.base",
        "mbmon.sinks.parquet",
    ],
)
def test_optional_analysis_is_not_imported_unless_asked(module: str) -> None:
    code = f"import sys, {module}; print(','.join(m for m in {OPTIONAL!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"{module} imports {out.stdout.strip()}"


def test_a_dissector_without_detection_does_not_import_it() -> None:
    code = (
        "import sys; from mbmon.sources.dissect import CaptureConfig, Dissector; "
        "Dissector(CaptureConfig()); a = 'mbmon.analysis.detect' in sys.modules; "
        "Dissector(CaptureConfig(detect=True)); "
        "print(a, 'mbmon.analysis.detect' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "True"]
