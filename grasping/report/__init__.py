"""The trial report: one self-contained ``DIR/report.html`` per trial run (``posegrasp report DIR``).

It holds the summary (success with its Wilson 95 % interval), the per-block and failure tables, success
against pose error, and sample frames like the paper's Fig. 9-10: a few episodes are re-simulated from their
recorded seeds up to the look capture (``grasping.episode``'s own functions, so the frame is the one the
provider saw) and drawn with the segmentation (the model's labels, or the ground-truth mask for the
oracles) and the block models rendered by pyrender at the estimated and at the true pose. The strip shows
the overview camera at the look pose of several episodes (episodes do not expose mid-episode frames).
A bin-picking run's page shows instead its ``bin_pick`` statistics and, for a few episodes, every attempt.
Everything is embedded (PNG/JPEG/GIF data URIs, inline CSS); the page needs no network.

Its parts, one concept each:

- ``run``: the run folder read into typed records (``TrialRun``: campaign, ``EpisodeRecord``s, ``Summary``);
- ``resim``: an episode re-simulated up to its look capture (``Look``);
- ``binpick``: a bin-picking episode replayed whole from its seeds (``BinReplay``: the tote before and after,
  a film from the overview camera, each failed attempt's capture with its estimates), for the oracle providers;
- ``figures``: the images (overlays, the success-against-error plot) as arrays and data URIs;
- ``sections``: the page, one function per section, each taking typed records and returning HTML;
- ``page``: ``write_report``, which picks the episodes to show and assembles the sections, and the command.
"""

from posegrasp.grasping.report.page import REPORT, register, run_report_cmd, write_report
from posegrasp.grasping.report.resim import Look, resimulate_look
from posegrasp.grasping.report.run import Summary, TrialRun, read_run

__all__ = ["REPORT", "Look", "Summary", "TrialRun", "read_run", "register", "resimulate_look", "run_report_cmd",
           "write_report"]
