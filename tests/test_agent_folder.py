"""agents.loading checks an agent folder as a whole before anything is scored: a damaged field of
metadata.json, a statistics file that is not the agent's, or a model whose spaces are not the env's
is one ValueError of one line naming the file and the field, and blf-eval says it in one line
(exit 2), instead of a silent wrong score or a long traceback."""

from __future__ import annotations

import hashlib
import json
import pickle
import warnings
import shutil
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from agents.evaluate import main as eval_main  # noqa: E402
from agents.loading import algorithm_class, load_agent, pretrained_agents  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PRETRAINED = ROOT / "agents" / "pretrained"
FILES = ("model.zip", "metadata.json", "vecnormalize.pkl")


def _copy(tmp_path: Path, name: str) -> Path:
    folder = tmp_path / name
    folder.mkdir()
    for f in FILES:
        shutil.copy(PRETRAINED / name / f, folder / f)
    return folder


def _meta(edit: Callable[[dict], None]) -> Callable[[Path], None]:
    def damage(folder: Path) -> None:
        meta = json.loads((folder / "metadata.json").read_text())
        edit(meta)
        (folder / "metadata.json").write_text(json.dumps(meta, indent=2))
    return damage


def _env(key: str, value) -> Callable[[Path], None]:
    return _meta(lambda m: m["env_kwargs"].__setitem__(key, value))


def _unlink_stats(folder: Path) -> None:
    (folder / "vecnormalize.pkl").unlink()


def _no_config_no_stats(folder: Path) -> None:
    _meta(lambda m: m.pop("config"))(folder)
    _unlink_stats(folder)


def _stats(edit: Callable) -> Callable[[Path], None]:
    def damage(folder: Path) -> None:
        with open(folder / "vecnormalize.pkl", "rb") as f:
            norm = pickle.load(f)
        edit(norm)
        # VecNormalize drops these when pickled (and so lacks them once unpickled)
        norm.venv, norm.class_attributes, norm.returns = None, {}, None
        with open(folder / "vecnormalize.pkl", "wb") as f:
            pickle.dump(norm, f)
    return damage


def _other_shape(norm) -> None:
    from stable_baselines3.common.running_mean_std import RunningMeanStd

    norm.obs_rms = RunningMeanStd(shape=(37,))  # a privileged agent's statistics


def _model(edit: Callable) -> Callable[[Path], None]:
    def damage(folder: Path) -> None:
        model = algorithm_class("ppo").load(folder / "model.zip", device="cpu")
        edit(model)
        model.save(folder / "model.zip")
    return damage


def _wider_observation(model) -> None:
    from gymnasium import spaces

    box = model.observation_space
    model.observation_space = spaces.Box(box.low * 2, box.high * 2, dtype=np.float32)


def _wider_action(model) -> None:
    from gymnasium import spaces

    model.action_space = spaces.Box(-2.0, 2.0, (3,), dtype=np.float32)


# (id, shipped agent, damage, file the message starts with, field it names)
CASES = [
    ("no-config-no-stats", "ppo_residual", _no_config_no_stats, "metadata.json", "config.normalize"),
    ("normalize-not-in-config", "ppo_residual", _meta(lambda m: m["config"].pop("normalize")),
     "metadata.json", "config.normalize"),
    ("normalize-not-a-bool", "ppo_residual", _meta(lambda m: m["config"].__setitem__("normalize", "yes")),
     "metadata.json", "config.normalize"),
    ("normalize-false-stats-present", "ppo_residual",
     _meta(lambda m: m["config"].__setitem__("normalize", False)), "metadata.json", "config.normalize"),
    ("normalize-true-stats-missing", "ppo_residual", _unlink_stats, "vecnormalize.pkl", "config.normalize"),
    ("mode-plain-on-residual", "ppo_residual", _meta(lambda m: m.__setitem__("mode", "plain")),
     "metadata.json", "mode"),
    ("mode-residual-on-plain", "ppo_plain", _meta(lambda m: m.__setitem__("mode", "residual")),
     "metadata.json", "mode"),
    ("mode-junk", "ppo_residual", _meta(lambda m: m.__setitem__("mode", "junk")), "metadata.json", "mode"),
    ("controller-none-on-residual", "ppo_residual", _env("controller", "none"), "metadata.json", "mode"),
    ("env_id-contradicts-mode", "ppo_residual", _meta(lambda m: m.__setitem__("env_id", "PlanarBLF-v0")),
     "metadata.json", "env_id"),
    ("env_kwargs-not-an-object", "ppo_residual", _meta(lambda m: m.__setitem__("env_kwargs", "x")),
     "metadata.json", "env_kwargs"),
    ("residual_scale-not-a-number", "ppo_residual", _env("residual_scale", "x"), "metadata.json",
     "env_kwargs.residual_scale"),
    ("unknown-env-key", "ppo_residual", _env("foo", 1), "metadata.json", "env_kwargs.foo"),
    ("privileged", "ppo_residual", _env("privileged", True), "metadata.json", "env_kwargs.privileged"),
    ("control_period-not-whole-ms", "ppo_residual", _env("control_period", 0.0105), "metadata.json",
     "env_kwargs.control_period"),
    ("observation_extras", "ppo_residual", _env("observation_extras", ["u_law"]), "metadata.json",
     "env_kwargs.observation_extras"),
    ("observation_extras-plain", "ppo_plain", _env("observation_extras", ["u_law"]), "metadata.json",
     "env_kwargs.observation_extras"),
    ("name-null", "ppo_residual", _meta(lambda m: m.__setitem__("name", None)), "metadata.json", "name"),
    ("stats-of-another-shape", "ppo_residual", _stats(_other_shape), "vecnormalize.pkl", "obs_rms"),
    ("stats-not-normalizing", "ppo_residual", _stats(lambda n: setattr(n, "norm_obs", False)),
     "vecnormalize.pkl", "norm_obs"),
    ("model-observation-bounds", "ppo_residual", _model(_wider_observation), "model.zip", "observation_space"),
    ("model-action-bounds", "ppo_plain", _model(_wider_action), "model.zip", "action_space"),
]


@pytest.mark.parametrize("agent,damage,file,field", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_a_damaged_field_is_one_line_naming_the_file_and_the_field(tmp_path, agent, damage, file, field):
    folder = _copy(tmp_path, agent)
    damage(folder)
    with pytest.raises(ValueError) as info:
        load_agent(folder)
    msg = str(info.value)
    assert "\n" not in msg, msg
    where = f"{folder / file}: "
    assert msg.startswith(where), msg
    if file == "vecnormalize.pkl" and "missing" in msg:
        assert field in msg, msg  # the message of old ("<file>: missing. ... config.normalize ...")
    else:
        assert msg[len(where):].startswith(field), msg  # "<file>: <field>...: <what is wrong>"


CLI_CASES = ["no-config-no-stats", "privileged", "residual_scale-not-a-number", "mode-junk", "unknown-env-key"]


@pytest.mark.parametrize("case", CLI_CASES)
def test_blf_eval_refuses_a_damaged_folder_in_one_line(tmp_path, capsys, case):
    _, agent, damage, file, field = next(c for c in CASES if c[0] == case)
    folder = _copy(tmp_path, agent)
    damage(folder)
    capsys.readouterr()
    rc = eval_main(["--agents", str(folder), "--controllers", "--scenarios", "paper-0.1hz", "--suite-seeds", "0",
                    "--duration", "1", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "Traceback" not in err
    errors = [line for line in err.splitlines() if line.startswith("blf-eval: error:")]
    assert len(errors) == 1, err
    assert errors[0].startswith(f"blf-eval: error: {folder / file}:") and field in errors[0]
    # anything else on stderr is the one-time compile notice
    assert all(line.startswith(("blf-eval: error:", "blf-gym: compiling")) for line in err.splitlines() if line)


@pytest.mark.parametrize("name", pretrained_agents())
def test_every_shipped_agent_folder_passes_the_checks(name):
    from agents.loading import check_agent_folder

    meta = json.loads((PRETRAINED / name / "metadata.json").read_text())
    assert meta["config"]["normalize"] is True
    model, meta2, norm = load_agent(PRETRAINED / name)
    assert meta2 == meta and norm is not None
    assert norm.obs_rms.mean.shape == model.observation_space.shape
    assert check_agent_folder(PRETRAINED / name / "model.zip") is None


TINY = """
n_envs: 2
env:
  control_period: 0.01
  duration: 0.2
hyperparams: {n_steps: 32, batch_size: 32, n_epochs: 1}
policy_kwargs:
  net_arch: [8]
eval_freq: 1000
checkpoint_freq: 64
curve_suite_seeds: 1
"""


def test_blf_train_states_normalize_even_when_the_config_leaves_it_out(tmp_path):
    from agents.train import main as train_main

    cfg = tmp_path / "c.yaml"
    cfg.write_text(TINY)  # no normalize: blf-train trains without normalization
    out = tmp_path / "run"
    assert train_main(["--algo", "ppo", "--timesteps", "64", "--config", str(cfg), "--out", str(out),
                       "--no-progress"]) == 0
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["config"]["normalize"] is False and not (out / "vecnormalize.pkl").exists()
    # the folder records the sha256 of what it saved, computed here with hashlib on the bytes on disk
    assert meta["files"] == {"model.zip": hashlib.sha256((out / "model.zip").read_bytes()).hexdigest()}
    _, _, norm = load_agent(out)
    assert norm is None
    # the stated default is not a difference from the same YAML on --resume
    assert train_main(["--algo", "ppo", "--timesteps", "128", "--config", str(cfg), "--out", str(out),
                       "--resume", "--no-progress"]) == 0
    assert json.loads((out / "metadata.json").read_text())["timesteps"] >= 128


def _swap_stats(folder: Path, other: str = "ppo_lagrangian") -> None:
    """Another shipped agent's statistics, of the same observation size: every structural check passes."""
    shutil.copy(PRETRAINED / other / "vecnormalize.pkl", folder / "vecnormalize.pkl")


def test_a_swapped_statistics_file_is_refused_by_name_unless_accepted(tmp_path):
    folder = _copy(tmp_path, "ppo_residual_certified")
    _swap_stats(folder)
    with pytest.raises(ValueError) as info:
        load_agent(folder)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(f"{folder / 'vecnormalize.pkl'}: sha256 "), msg
    assert "accept_changed_files=True" in msg and "--accept-changed-files" in msg
    model, meta, norm = load_agent(folder, accept_changed_files=True)
    with open(PRETRAINED / "ppo_lagrangian" / "vecnormalize.pkl", "rb") as f:
        np.testing.assert_array_equal(norm.obs_rms.mean, pickle.load(f).obs_rms.mean)  # the swapped one, as asked


@pytest.mark.parametrize("damage,word", [
    (lambda f: (f / "vecnormalize.pkl").write_bytes((f / "vecnormalize.pkl").read_bytes() + b"\0"), "sha256"),
    (_meta(lambda m: m["files"].pop("vecnormalize.pkl")), "do not list it"),
    (_meta(lambda m: m["files"].__setitem__("model.zip", "0" * 64)), "sha256"),
])
def test_a_file_that_is_not_the_saved_one_or_not_listed_is_refused(tmp_path, damage, word):
    folder = _copy(tmp_path, "ppo_residual")
    damage(folder)
    with pytest.raises(ValueError, match=word):
        load_agent(folder)


def test_a_folder_without_hashes_loads_with_one_warning_and_can_record_them(tmp_path):
    from agents.loading import main as loading_main

    folder = _copy(tmp_path, "ppo_residual")
    _meta(lambda m: m.pop("files"))(folder)
    with pytest.warns(UserWarning, match="no 'files' field") as record:
        load_agent(folder)
    assert len(record) == 1 and "\n" not in str(record[0].message)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_agent(folder)  # once per folder and process
    assert loading_main(["--record-hashes", str(folder)]) == 0
    assert json.loads((folder / "metadata.json").read_text())["files"] == \
        json.loads((PRETRAINED / "ppo_residual" / "metadata.json").read_text())["files"]


def test_blf_eval_refuses_a_swapped_file_and_scores_it_when_told(tmp_path, capsys):
    folder = _copy(tmp_path, "ppo_residual")
    _swap_stats(folder)
    args = ["--agents", str(folder), "--controllers", "--scenarios", "paper-0.1hz", "--suite-seeds", "0",
            "--duration", "0.5", "--no-progress"]
    capsys.readouterr()
    assert eval_main(args) == 2
    err = capsys.readouterr().err
    assert f"blf-eval: error: {folder / 'vecnormalize.pkl'}: sha256" in err and "Traceback" not in err
    assert eval_main(args + ["--accept-changed-files"]) == 0
