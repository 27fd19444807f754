"""Pipeline files: validation with key paths, the DAG, and bad configs through the CLI."""

from __future__ import annotations

import pytest
from pipeline_toys import TOY_PIPELINE

from imupipe import cli
from imupipe.errors import ConfigError
from imupipe.pipeline import api, config
from imupipe.pipeline.config import load_pipeline


def _write(tmp_path, text, name="p.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def _error(tmp_path, registry, text) -> str:
    path = _write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_pipeline(path, registry)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"{path}: ")
    return message[len(f"{path}: ") :]


def test_valid_pipeline_is_wired_in_topological_order(tmp_path, toy_registry):
    registry, _ = toy_registry()
    pipeline = load_pipeline(_write(tmp_path, TOY_PIPELINE), registry)
    order = list(pipeline.nodes)
    assert order.index("scaled") < order.index("accel")
    assert set(order) == {"scaled", "accel", "gyro", "mag"}
    assert pipeline.nodes["mag"].solver.solver.name == "toy_mean"
    assert pipeline.nodes["mag"].solver.params.scale == 1.0
    assert pipeline.nodes["scaled"].params.factor == 1.0
    assert [str(r) for r in pipeline.export_calibration] == [
        "accel.calibration",
        "gyro.calibration",
        "mag.calibration",
    ]
    assert pipeline.downstream("scaled") == {"accel"}


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        # typo in a stage's params: validated by the stage's own Params model, with a suggestion
        (
            "factor = 1.0",
            "factr = 1.0",
            "stages.scaled.params.factr: unknown key; did you mean 'factor'?",
        ),
        # typo in a stage section
        (
            'uses = "toy_bias_gyro"',
            'use = "toy_bias_gyro"',
            "stages.gyro.use: unknown key; did you mean 'uses'?",
        ),
        # typo at the top level
        (
            'description = "toy',
            'descripton = "toy',
            "descripton: unknown key; did you mean 'description'?",
        ),
        # wrong type
        (
            "factor = 1.0",
            'factor = "big"',
            "stages.scaled.params.factor: Input should be a valid number",
        ),
        # solver params validated by the solver's model
        (
            "solver_params = { scale = 1.0 }",
            "solver_params = { scael = 1.0 }",
            "stages.mag.params.solver_params.scael: unknown key; did you mean 'scale'?",
        ),
        (
            "solver_params = { scale = 1.0 }",
            'solver = "toy_other_kind"',
            (
                "stages.mag.params.solver: solver 'toy_other_kind' is of kind 'other'; "
                "stage 'toy_bias_mag' needs kind 'toy'"
            ),
        ),
        (
            "solver_params = { scale = 1.0 }",
            'solver = "nope"',
            "stages.mag.params.solver: no solver named 'nope'",
        ),
        # unknown stage
        (
            'uses = "toy_bias_gyro"',
            'uses = "toy_bias_gyr"',
            "stages.gyro.uses: no stage named 'toy_bias_gyr'",
        ),
        # dangling reference
        (
            'samples = "scaled.samples"',
            'samples = "scaledd.samples"',
            "stages.accel.inputs.samples: refers to stage 'scaledd', which is not in this pipeline",
        ),
        # unknown output
        (
            'samples = "scaled.samples"',
            'samples = "scaled.sample"',
            "stages.accel.inputs.samples: stage 'scaled' (toy_scale) has no output 'sample'",
        ),
        # unknown session stream
        (
            'samples = "session.gyro"',
            'samples = "session.gyros"',
            "stages.gyro.inputs.samples: no session stream 'gyros'",
        ),
        # schema mismatch on an edge
        (
            'samples = "session.gyro"',
            'samples = "session.accel"',
            (
                "stages.gyro.inputs.samples: 'session.accel' is a table of schema 'accel', "
                "but input 'samples' of stage "
                "'toy_bias_gyro' expects schema 'gyro'"
            ),
        ),
        # unknown input port and missing required input
        (
            'samples = "session.mag"',
            'sample = "session.mag"',
            "stages.mag.inputs.sample: stage 'toy_bias_mag' has no input",
        ),
        (
            'inputs = { samples = "session.mag" }',
            "inputs = {}",
            "stages.mag.inputs: stage 'toy_bias_mag' needs input(s) samples",
        ),
        # not a reference
        (
            'samples = "session.mag"',
            'samples = "mag"',
            "stages.mag.inputs.samples: 'mag' is not a reference",
        ),
        # exports
        (
            '"mag.calibration"]',
            '"scaled.samples"]',
            (
                "export.calibration[2]: 'scaled.samples' is a table of schema 'accel', "
                "expected 'calibration'"
            ),
        ),
        (
            '"mag.calibration"]',
            '"magg.calibration"]',
            "export.calibration[2]: refers to stage 'magg'",
        ),
        # missing required key
        ('name = "toy"\n', "", "name: missing required key"),
        # the [input] section
        (
            "[export]",
            '[input]\ndevise = "imu"\n[export]',
            "input.devise: unknown key; did you mean 'device'?",
        ),
        (
            "[export]",
            '[input]\nreader = "nope"\n[export]',
            "input.reader: no reader named 'nope'",
        ),
    ],
)
def test_bad_config_names_file_and_key_path(tmp_path, toy_registry, old, new, expected):
    registry, _ = toy_registry()
    assert old in TOY_PIPELINE
    message = _error(tmp_path, registry, TOY_PIPELINE.replace(old, new, 1))
    assert message.startswith(expected), message


def test_cycle_is_rejected(tmp_path, toy_registry):
    registry, _ = toy_registry()
    text = TOY_PIPELINE.replace(
        'inputs = { samples = "session.accel" }', 'inputs = { samples = "again.samples" }'
    )
    text += '\n[stages.again]\nuses = "toy_scale"\ninputs = { samples = "scaled.samples" }\n'
    message = _error(tmp_path, registry, text)
    assert message.startswith("stages: the inputs form a cycle")
    assert "scaled" in message and "again" in message


def test_invalid_toml_and_reserved_stage_key(tmp_path, toy_registry):
    registry, _ = toy_registry()
    assert _error(tmp_path, registry, "name = ").startswith("not valid TOML")
    text = TOY_PIPELINE.replace("[stages.gyro]", "[stages.session]")
    assert _error(tmp_path, registry, text).startswith(
        "stages.session: 'session' cannot name a stage"
    )


def test_default_pipeline_missing_is_a_clear_error(tmp_path, monkeypatch, toy_registry):
    registry, _ = toy_registry()
    monkeypatch.setattr(
        config, "default_pipeline_path", lambda: tmp_path / "pipelines" / "default.toml"
    )
    with pytest.raises(
        ConfigError, match="the default pipeline is missing; give one with --pipeline"
    ):
        load_pipeline(None, registry)


def test_default_pipeline_location_is_beside_the_package():
    import imupipe

    path = config.default_pipeline_path()
    assert path.name == "default.toml"
    assert path.parent.parent == config.Path(imupipe.__file__).resolve().parent.parent


@pytest.mark.parametrize(
    ("old", "new", "key"),
    [
        ("factor = 1.0", "factr = 1.0", "stages.scaled.params.factr"),
        ('uses = "toy_bias_gyro"', 'uses = "nope"', "stages.gyro.uses"),
        ('samples = "session.mag"', 'samples = "nowhere.out"', "stages.mag.inputs.samples"),
        ("factor = 1.0", "factor = [1]", "stages.scaled.params.factor"),
    ],
)
@pytest.mark.parametrize("command", ["run", "batch"])
def test_cli_bad_config_exits_2_with_one_line_and_writes_nothing(
    tmp_path, toy_registry, monkeypatch, capsys, session, old, new, key, command
):
    registry, counter = toy_registry()
    monkeypatch.setattr(api, "make_registry", lambda *a, **k: registry)
    from pipeline_toys import TOY_SPEC

    monkeypatch.setattr(api, "DEFAULT_SPEC", TOY_SPEC)
    bad = _write(tmp_path, TOY_PIPELINE.replace(old, new, 1), "bad.toml")
    out = tmp_path / "out"
    status = cli.main([command, str(session), "--pipeline", str(bad), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert status == 2
    assert err.count("\n") == 1
    assert f"{bad}: {key}:" in err
    assert not out.exists()
    assert counter.ran == []


def test_cli_status_bad_config_exits_2(tmp_path, toy_registry, monkeypatch, capsys):
    registry, _ = toy_registry()
    monkeypatch.setattr(api, "make_registry", lambda *a, **k: registry)
    bad = _write(tmp_path, TOY_PIPELINE.replace("factor = 1.0", "factr = 1.0"), "bad.toml")
    assert cli.main(["status", "--pipeline", str(bad), "--out", str(tmp_path / "out")]) == 2
    assert "stages.scaled.params.factr: unknown key" in capsys.readouterr().err


SHIPPED = sorted(config.default_pipeline_path().parent.glob("*.toml"))


@pytest.mark.skipif(not SHIPPED, reason="no pipelines/*.toml shipped yet")
@pytest.mark.parametrize("path", SHIPPED, ids=[p.name for p in SHIPPED])
def test_every_shipped_pipeline_validates_against_the_installed_plugins(path):
    from imupipe.plugins import make_registry

    pipeline = load_pipeline(path, make_registry())
    assert pipeline.nodes and pipeline.name
    assert all(r.source in pipeline.nodes for r in pipeline.export_calibration)


def test_cli_cycle_exits_2_and_writes_nothing(tmp_path, toy_registry, monkeypatch, capsys, session):
    registry, counter = toy_registry()
    monkeypatch.setattr(api, "make_registry", lambda *a, **k: registry)
    text = TOY_PIPELINE.replace(
        'inputs = { samples = "session.accel" }', 'inputs = { samples = "again.samples" }'
    )
    text += '\n[stages.again]\nuses = "toy_scale"\ninputs = { samples = "scaled.samples" }\n'
    bad = _write(tmp_path, text, "cycle.toml")
    out = tmp_path / "out"
    assert (
        cli.main(["run", str(session), "--pipeline", str(bad), "--out", str(out), "--quiet"]) == 2
    )
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{bad}: stages: the inputs form a cycle" in err
    assert not out.exists() and counter.ran == []
