"""The shipped run configs of `sandbox` and `controlnet` carry the paper's hyperparameters and
their model tables match the code's defaults; the shipped accelerate configs are valid for the
installed accelerate. (No model is built here.)"""

from __future__ import annotations

import dataclasses
import importlib.resources

import pytest

pytest.importorskip("torch")
pytest.importorskip("diffusers")
accelerate = pytest.importorskip("accelerate")

from morphgs.configfile import ConfigError, config_from_dict  # noqa: E402
from morphgs.training.config import resolve_config  # noqa: E402


def test_sandbox_defaults_are_the_papers() -> None:
    cfg = resolve_config("sandbox", None, {}).config
    m = cfg.model_config
    assert (m["lora_rank"], m["lora_alpha"], m["lora_dropout"]) == (64, 128.0, 0.05)
    assert m["lora_targets"] == ["to_q", "to_k", "to_v", "to_out.0"]
    assert (m["conv_in_channels"], m["conv_in_cond_scale"]) == (8, 0.1)
    assert m["prompt"] == "remove degradation"
    o = cfg.optim
    assert (o.lr, o.betas, o.weight_decay, o.schedule, o.warmup, o.grad_clip) == (2e-4, (0.9, 0.999), 1e-2,
                                                                                  "cosine", 0.05, 1.0)
    assert (cfg.data.batch_size, o.grad_accum, cfg.data.frames) == (1, 4, 16)
    assert cfg.run.mixed_precision == "auto"  # bf16 where the hardware has it


def test_controlnet_defaults_are_the_papers() -> None:
    cfg = resolve_config("controlnet", None, {}).config
    m = cfg.model_config
    assert (m["controlnet_blocks"], m["controlnet_stride"]) == (8, 3)
    assert (cfg.data.frames, cfg.data.size) == (49, (480, 832))
    assert m["inference_steps"] == 50 and m["gradient_checkpointing"] is True and m["weight_dtype"] == "bfloat16"


@pytest.mark.parametrize("model", ["sandbox", "controlnet"])
def test_shipped_model_tables_state_the_code_defaults(model: str) -> None:
    if model == "sandbox":
        from morphgs.diffusion.sandbox_refiner import SandboxSettings as Settings
        required = {"sd15": "x", "motion_adapter": "y"}
    else:
        from morphgs.diffusion.controlnet_refiner import ControlNetSettings as Settings  # type: ignore[assignment]
        required = {"wan": "x"}
    table = dict(resolve_config(model, None, {}).config.model_config)
    settings = config_from_dict(Settings, {**table, **required}, section="model")
    for f in dataclasses.fields(Settings):
        if f.name in table and f.name not in required:
            default = f.default
            assert getattr(settings, f.name) == (tuple(default) if isinstance(default, list) else default), f.name
    with pytest.raises(ConfigError, match=next(iter(required))):
        config_from_dict(Settings, table, section="model")  # the folders must be given


@pytest.mark.parametrize("model", ["sandbox", "controlnet"])
def test_without_the_diffusion_extra_the_cli_says_what_to_install(model: str, tmp_path) -> None:
    import subprocess
    import sys

    code = ("import sys; sys.modules['diffusers'] = None\n"  # as if diffusers were not installed
            "from morphgs import cli\n"
            f"sys.exit(cli.main(['train', '--model', '{model}', '--out', r'{tmp_path / 'run'}']))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 1, done.stderr[-2000:]
    assert "pip install 'morphgs[diffusion]'" in done.stderr and "Traceback" not in done.stderr


def _launch_options() -> set[str]:
    from accelerate.commands.launch import launch_command_parser

    return {a.dest for a in launch_command_parser()._actions}


@pytest.mark.parametrize("name", ["fsdp2_8gpu.yaml", "deepspeed_zero2_8gpu.yaml", "ddp_8gpu.yaml"])
def test_accelerate_configs_load(name: str, tmp_path) -> None:
    from accelerate.commands.config.config_args import ClusterConfig

    text = importlib.resources.files("morphgs.configs").joinpath("accelerate", name).read_text()
    path = tmp_path / name
    path.write_text(text)
    cfg = ClusterConfig.from_yaml_file(str(path))  # refuses unknown top-level keys
    assert cfg.num_processes == 8 and cfg.mixed_precision == "bf16"
    nested = {**(cfg.fsdp_config or {}), **(cfg.deepspeed_config or {})}
    unknown = set(nested) - _launch_options()
    assert not unknown, f"{name}: keys accelerate launch does not know: {sorted(unknown)}"
    if name.startswith("fsdp"):
        assert cfg.fsdp_config["fsdp_transformer_layer_cls_to_wrap"] == "WanTransformerBlock"
        assert cfg.fsdp_config["fsdp_version"] == 2
    if name.startswith("deepspeed"):
        assert cfg.deepspeed_config["zero_stage"] == 2
