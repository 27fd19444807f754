"""The plugin registry as the pipeline relies on it: duplicates, readers, listing."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pipeline_toys
import pytest

import imupipe.plugins
from imupipe import cli
from imupipe.errors import PluginError, ReaderError
from imupipe.hookspecs import hookimpl
from imupipe.ingest import choose_reader, read_recording
from imupipe.plugins import make_registry


class _Reader:
    suffixes = (".arrowsession",)

    def __init__(self, name):
        self.name = name

    def sniff(self, path, head):
        return Path(path).suffix == ".arrowsession"

    def read(self, path):
        return pipeline_toys.ArrowSessionReader().read(path)


class _ReaderPlugin:
    def __init__(self, name):
        self.reader = _Reader(name)

    @hookimpl
    def imupipe_register_readers(self, register):
        register(self.reader)


def test_duplicate_component_names_name_both_plugins():
    class Again:
        @hookimpl
        def imupipe_register_stages(self, register):
            register(pipeline_toys.make_scale())

    pm_first, pm_second = pipeline_toys.ToyPlugin(), Again()
    registry = make_registry([pm_first, pm_second], entry_points_too=False)
    with pytest.raises(PluginError) as info:  # raised when the kind is first looked up
        registry.names("stages")
    message = str(info.value)
    assert "two plugins register a stage named 'toy_scale'" in message
    # both plugins are named (pluggy names a plugin object registered without a name by its id)
    assert f"'{id(pm_first)}' and '{id(pm_second)}'" in message
    assert "uninstall one" in message


def test_a_kind_is_registered_only_when_first_looked_up():
    """``imupipe ingest`` needs the readers: the solvers' modules (scipy, polars) stay unimported;
    registering every kind imports no scipy (imu_tk's pipeline runs without it)."""
    code = (
        "import sys\n"
        "from imupipe.plugins import make_registry\n"
        "r = make_registry()\n"
        "assert 'mcap' in r.names('readers')\n"
        "heavy = [m for m in ('imupipe.solvers.joint_ml', 'imupipe.stages.refine', 'polars', 'pydantic',\n"
        "                     'scipy.optimize', 'imupipe.diagnosis.residual_map', 'mcap.reader',\n"
        "                     'multiprocessing') if m in sys.modules]\n"
        "assert not heavy, heavy\n"
        "assert 'joint_ml' in r.names('solvers')\n"
        "assert 'imupipe.solvers.joint_ml' in sys.modules\n"
        "for kind in ('stages', 'exporters', 'executors', 'effects'):\n"
        "    r.names(kind)\n"
        "# every component registered: what only running them needs is still not imported (a\n"
        "# helper module listing no components, the joint fit's algebra, is not imported for it)\n"
        "heavy = [m for m in ('ruptures', 'matplotlib', 'distributed', 'scipy.optimize', 'scipy.linalg',\n"
        "                     'scipy.sparse', 'scipy.special', 'imupipe.solvers.blocktri',\n"
        "                     'imupipe.diagnosis.residual_map', 'mcap.reader', 'multiprocessing')\n"
        "         if m in sys.modules]\n"
        "assert not heavy, heavy\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_imu_tk_pipeline_runs_without_scipy_or_arrow_compute(shared_data, tmp_path):
    """imu_tk's pipeline (method B's solvers, the report) needs neither SciPy nor Arrow's compute
    kernels: a run imports neither (their imports were a third of the whole process), nor, on
    its text files, the MCAP library's reader."""
    root = Path(__file__).resolve().parents[2]
    code = (
        "import sys\n"
        "from imupipe import cli\n"
        f"status = cli.main(['run', {str(root / 'examples' / 'sessions' / 'imu_tk_xsens.toml')!r}, '--pipeline',\n"
        f"                   {str(root / 'pipelines' / 'imu_tk.toml')!r}, '--out', {str(tmp_path)!r}, '--quiet'])\n"
        "assert status == 0, status\n"
        "loaded = [m for m in sys.modules if m in ('scipy', 'pyarrow.compute', 'mcap.reader')\n"
        "          or m.startswith('scipy.')]\n"
        "assert not loaded, loaded\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_reading_a_recording_imports_only_what_it_uses():
    """``imupipe ingest``: the params' models and Arrow's compute kernels are a quarter of its
    imports; a reader's tables come out in their schema's types without a cast, nor through
    ``pa.array``'s check for masked arrays (it imports numpy.ma); the batch executors' process
    pools are not loaded to register them."""
    example = Path(__file__).resolve().parents[2] / "examples" / "standard-session.mcap"
    code = (
        "import sys\n"
        "from imupipe.ingest import read_recording\n"
        "from imupipe.plugins import make_registry\n"
        f"rec = read_recording({str(example)!r}, make_registry())\n"
        "assert rec.device()['accel'].num_rows > 0\n"
        "heavy = [m for m in ('pydantic', 'pyarrow.compute', 'numpy.ma', 'multiprocessing') if m in sys.modules]\n"
        "assert not heavy, heavy\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_two_claimants_is_an_error_naming_both(tmp_path):
    registry = make_registry([_ReaderPlugin("one"), _ReaderPlugin("two")], entry_points_too=False)
    path = pipeline_toys.write_session(tmp_path / "s.arrowsession")
    with pytest.raises(ReaderError, match="readers 'one' and 'two' both claim this file"):
        choose_reader(path, registry)


def test_reader_choice_is_a_firstresult_hook_a_plugin_can_win(tmp_path):
    class Chooser:
        def __init__(self):
            self.asked = []

        @hookimpl
        def imupipe_choose_reader(self, path, head, readers):
            self.asked.append(sorted(readers))
            return "two" if path.suffix == ".arrowsession" else None

    chooser = Chooser()
    registry = make_registry(
        [_ReaderPlugin("one"), _ReaderPlugin("two"), chooser], entry_points_too=False
    )
    path = pipeline_toys.write_session(tmp_path / "s.arrowsession", streams=("accel",))
    assert choose_reader(path, registry).name == "two"  # the built-in (trylast) never sees the tie
    assert chooser.asked == [["one", "two"]]
    assert set(read_recording(path, registry).device()) == {"accel"}


def test_imupipe_plugins_lists_name_distribution_version_and_provides(monkeypatch, capsys):
    real = make_registry()  # entry points: the built-ins come through the same door as plugins
    names = {c.plugin for c in real.all()}
    assert "builtin_exporters" in names and "builtin_executors" in names
    monkeypatch.setattr(
        imupipe.plugins,
        "make_registry",
        lambda *a, **k: make_registry([pipeline_toys], entry_points_too=True),
    )
    assert cli.main(["plugins"]) == 0
    text = capsys.readouterr().out
    lines = text.splitlines()
    i = next(i for i, line in enumerate(lines) if line.startswith("builtin_executors"))
    assert f"(imupipe {imupipe.__version__})" in lines[i]
    assert "executor:dask" in lines[i + 1] and "executor:local" in lines[i + 1]
    j = next(i for i, line in enumerate(lines) if line.startswith("builtin_exporters"))
    assert "exporter:calibration_json" in lines[j + 1]
    k = next(i for i, line in enumerate(lines) if "pipeline_toys" in line)
    assert "(-" in lines[k]  # not from an installed distribution
    assert (
        "reader:arrowsession" in lines[k + 1]
        and "stage:toy_scale" in lines[k + 1]
        and "solver:toy_mean" in lines[k + 1]
    )


class _FakeDist:
    """An installed distribution as ``importlib.metadata`` shows it, with imupipe entry points."""

    def __init__(self, name, entry_points):
        from importlib import metadata

        self.metadata = {"name": name}
        self.version = "9.9"
        self.entry_points = [metadata.EntryPoint(n, v, "imupipe") for n, v in entry_points]


def _with_fake_dists(monkeypatch, *fakes):
    from importlib import metadata

    real = list(metadata.distributions())
    monkeypatch.setattr(metadata, "distributions", lambda: [*fakes, *real])


def test_plugin_failing_at_import_is_listed_broken_and_the_rest_works(monkeypatch, capsys):
    _with_fake_dists(monkeypatch, _FakeDist("evil-imu", [("evil", "no_such_module_xyz")]),
                     _FakeDist("usurper", [("builtin_readers", "pipeline_toys")]))
    registry = make_registry()
    assert "csv" in registry.names("readers")  # the built-ins still work ...
    assert registry.get("readers", "csv").__module__.startswith("imupipe.")  # ... not replaced
    assert "arrowsession" not in registry.names("readers")  # the usurper's reader is not in
    assert "failed to import: ModuleNotFoundError" in registry.broken["evil"][2]
    assert "already imupipe's" in registry.broken["builtin_readers (usurper)"][2]
    assert cli.main(["plugins"]) == 0
    out = capsys.readouterr().out
    assert "evil  (evil-imu 9.9)  BROKEN" in out and "builtin_readers (usurper)" in out
    assert "reader:csv" in out


class _RaisingHook:
    @hookimpl
    def imupipe_register_readers(self, register):
        register(_Reader("half_registered"))
        raise RuntimeError("vendor SDK missing")


def test_plugin_raising_in_its_hook_is_left_out(caplog):
    registry = make_registry([_RaisingHook(), pipeline_toys], entry_points_too=False)
    assert "arrowsession" in registry.names("readers")
    assert "half_registered" not in registry.names("readers")
    ((_, (_, _, why)),) = registry.broken.items()
    assert "imupipe_register_readers raised RuntimeError: vendor SDK missing" in why
    assert "is broken and left out" in caplog.text
