"""Dataset generation settings: the shipped TOML documents the defaults; bad values are one-line errors."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

import posegrasp.datagen as datagen
from posegrasp.datagen.config import DatagenConfig, LightConfig, ViewConfig, load_datagen_config
from posegrasp.errors import ConfigError, UserError

SHIPPED = Path(datagen.__file__).parent / "datagen.toml"


def test_shipped_toml_equals_defaults():
    assert load_datagen_config(SHIPPED) == DatagenConfig()


@pytest.mark.parametrize("text, words", [
    ("blocks = [5, 2]\n", "blocks"),
    ("rgb_format = 'bmp'\n", "rgb_format"),
    ("msaa = 3\n", "msaa"),
    ("[textures]\nkinds = ['marble']\n", "textures: TextureConfig.kinds"),
    ("[lights]\nextra = [0, 9]\n", "lights.extra"),
    ("[views]\ndistance = [0.5]\n", "views: ViewConfig.distance"),
    ("[depth_noise]\nsigma_base = 'big'\n", "sigma_base"),
])
def test_bad_settings_name_the_setting(tmp_path, text, words):
    p = tmp_path / "c.toml"
    p.write_text(text)
    with pytest.raises(UserError, match=words):
        load_datagen_config(p)


@pytest.mark.parametrize("make, words", [
    (lambda: DatagenConfig(msaa=3), "DatagenConfig.msaa = 3"),
    (lambda: DatagenConfig(min_spacing=0.5), "DatagenConfig.min_spacing = 0.5 is out of range"),
    (lambda: ViewConfig(distance=(0.6, 0.3)), "ViewConfig.distance = [0.6, 0.3]"),
    (lambda: LightConfig(extra=(0, 7)), "LightConfig.extra = (0, 7) is out of range"),
])
def test_settings_refuse_bad_values_when_built(make, words):
    with pytest.raises(ConfigError, match=re.escape(words)):
        make()
