"""The trial report: one self-contained ``DIR/report.html`` per trial run (``posegrasp report DIR``).

It holds the summary (success with its Wilson 95 % interval), the per-block and failure tables, success
against pose error, and sample frames like the paper's Fig. 9-10: a few episodes are re-simulated from their
recorded seeds up to the look capture (``grasping.episode``'s own functions, so the frame is the one the
provider saw) and drawn with the segmentation (the model's labels, or the ground-truth mask for the
oracles) and the outlines of the block models projected at the estimated and at the true pose. The strip shows
the overview camera at the look pose of several episodes (episodes do not expose mid-episode frames).
A task with a page of its own (``Task.report_page``) shows that instead: bin picking's statistics and, for a few
episodes, every attempt (``grasping.tasks.bin_pick.report``).
Everything is embedded (PNG/JPEG/GIF data URIs, inline CSS); the page needs no network.

Its parts, one concept each:

- ``run``: the run folder read into typed records (``TrialRun``: campaign, ``EpisodeRecord``s, ``Summary``);
- ``resim``: an episode re-simulated up to its look capture (a ``figures.Look``);
- ``replay``: an episode replayed whole from its seeds (``Replay``: the scene before and after, a film from the
  overview camera, the captures a page asks for with their estimates), for the oracle providers;
- ``figures``: the images (overlays, the success-against-error plot) as arrays and data URIs;
- ``sections``: the page, one function per section, each taking typed records and returning HTML;
- ``page``: ``write_report``, which picks the episodes to show and assembles the sections, and the command.
"""

from posegrasp.grasping.report.page import REPORT, register, run_report_cmd, write_report
from posegrasp.grasping.report.figures import Look
from posegrasp.grasping.report.resim import resimulate_look
from posegrasp.grasping.report.run import Summary, TrialRun, read_run

__all__ = ["REPORT", "Look", "Summary", "TrialRun", "read_run", "register", "resimulate_look", "run_report_cmd",
           "write_report"]
