"""conf/model/*.yaml and conf/loss/*.yaml build a working DepthModule."""

from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from endorecon.module import DepthModule
from endorecon.networks import FCDenseNet, count_parameters

CONF = Path(__file__).resolve().parents[2] / "conf"


@pytest.mark.parametrize("name", ["fcdensenet_cpu", "fcdensenet57"])
def test_model_configs_build_and_run(name):
    model = OmegaConf.load(CONF / "model" / f"{name}.yaml")
    loss = OmegaConf.load(CONF / "loss" / "nll.yaml")
    module = DepthModule(model, loss)
    assert isinstance(module.net, FCDenseNet)
    assert module.weights == {"sparse_depth": 1.0, "depth_consistency": 0.5, "sparse_flow": 100.0, "dense_simulation": 0.1}
    assert module.eps == 1e-8
    if name == "fcdensenet57":
        assert 1.3e6 < count_parameters(module.net) < 1.45e6
    for hw in ((128, 160), (256, 320)):
        d, s = module.predict(torch.rand(1, 3, *hw), torch.ones(1, 1, *hw, dtype=torch.bool))
        assert d.shape == (1, 1, *hw) and torch.isfinite(d).all() and (s > 0).all()
    opt = OmegaConf.to_container(model.optimizer)
    assert opt["_partial_"] is True and model.scheduler._partial_ is True


def test_multirun_dirs_tell_apart_overrides_that_change_results():
    """A sweep over experiment or trainer (resolution, network, epochs, precision) put every job in one run dir:
    only keys that change no result may be left out of the job's subdir name."""
    hydra = OmegaConf.load(CONF / "hydra" / "default.yaml")
    excluded = set(hydra.job.config.override_dirname.exclude_keys)
    assert excluded <= {"debug", "logger", "callbacks", "paths.output_root", "paths.root_dir", "ckpt_path"}, excluded
    assert "paths.output_root" in excluded  # the sweep dir already lies under it (it was nested into the name)
