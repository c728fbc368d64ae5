"""``posegrasp quantize``: measure a run's int8 activation ranges on a dataset's images (``perception.int8``).

Each net observes the inputs it gets at inference through the estimator's own stages: the seg net the resized images,
the classifiers the crops of the images' segments, here the true ones (the class map of the visible masks, cut into
connected components), so the ranges do not hang on how well the seg net already finds the objects.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from posegrasp.errors import UserError
from posegrasp.outputs import check_out_file
from posegrasp.perception import int8
from posegrasp.perception.data import label_map, load_records
from posegrasp.perception.ensemble import ClassifierEnsemble
from posegrasp.perception.estimator import Estimator, EstimatorConfig


def calibrate(weights: str | Path, data: str | Path, split: str = "train_pbr", images: int = 32,
              progress: bool = True, force: bool = False) -> list[Path]:
    """Measure the int8 ranges of the run ``weights``'s seg net and classifiers on ``images`` images spread evenly over
    the BOP ``split`` of ``data`` (in its order) and write them into their checkpoint folders (``int8.RANGES``);
    returns the files written. UserError, before anything is written, where such a file is not one ``quantize`` wrote
    (without ``force``), and when a net saw no input (a classifier, where no image shows an object)."""
    from posegrasp.progress import track

    if not int8.supported():
        raise UserError("this torch has no oneDNN quantized engine, so its nets cannot run in int8")
    weights, data = Path(weights), Path(data)
    est = Estimator(weights, EstimatorConfig(int8=False))
    est.segmenter.model = int8.observing(est.segmenter.model)
    nets = [(weights / "seg", est.segmenter.model)]
    if est.classifier is not None:
        est.classifier.models = [int8.observing(m) for m in est.classifier.models]
        nets += list(zip(ClassifierEnsemble.members(weights), est.classifier.models))
    for ckpt, _ in nets:
        check_out_file(ckpt / int8.RANGES, int8.COMMAND, force=force, what="an int8 calibration", option="")
    records = load_records(data, split)
    picked = np.unique(np.linspace(0, len(records) - 1, min(images, len(records))).round().astype(int))
    for i in track(list(picked), "int8 ranges", enabled=progress):
        rec = records[i]
        rgb = rec.load_rgb()
        est.segment(rgb)
        if est.classifier is not None:
            est.classify(rgb, rec.load_depth(), rec.camera.K, label_map(rec, rgb.shape[:2]))
    measured = []
    for ckpt, model in nets:
        try:
            measured.append((ckpt, int8.ranges(model)))
        except ValueError:
            raise UserError(f"{ckpt.name} saw no input in {len(picked)} images of {data / split}: use images of the "
                            "run's objects") from None
    seen = [f"{records[i].scene_id}/{records[i].im_id}" for i in picked]
    source = {"data": str(data), "split": split, "images": seen}
    return [int8.write_ranges(ckpt, r, source) for ckpt, r in measured]
