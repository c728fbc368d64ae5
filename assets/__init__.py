"""The shipped assets, installed with the package: the block object set (``blocks/``), workcell settings
(``workcell.toml``), the hand-eye calibration (``calibration/``) and the shipped network (``perception/model/``)."""
