"""Camera video at the library's edge: read and write videos, track a shuttle or markers,
render synthetic frames. Needs the ``video`` extra (``pip install "greybox[video]"``:
scikit-image for sub-pixel registration, imageio and imageio-ffmpeg for containers).
"""

from greybox.io._video import VideoInfo as VideoInfo
from greybox.io._video import iter_frames as iter_frames
from greybox.io._video import prefetch as prefetch
from greybox.io._video import probe as probe
from greybox.io._video import read_frames as read_frames
from greybox.io._video import write_image_stack as write_image_stack
from greybox.io._video import write_video as write_video
from greybox.video._render import RenderedSequence as RenderedSequence
from greybox.video._render import exposure_times as exposure_times
from greybox.video._render import render_markers as render_markers
from greybox.video._render import render_shuttle as render_shuttle
from greybox.video._tracking import FeatureTracker as FeatureTracker
from greybox.video._tracking import Measurements as Measurements
from greybox.video._tracking import PoseTrack as PoseTrack
from greybox.video._tracking import Roi as Roi
from greybox.video._tracking import ShuttleTrack as ShuttleTrack
from greybox.video._tracking import Thresholds as Thresholds
from greybox.video._tracking import assess as assess
from greybox.video._tracking import measure_sequence as measure_sequence
from greybox.video._tracking import pose_track as pose_track
from greybox.video._tracking import reference_frame as reference_frame
from greybox.video._tracking import saturation_level_for as saturation_level_for
from greybox.video._tracking import search_crop as search_crop
from greybox.video._tracking import shuttle_track as shuttle_track
from greybox.video._tracking import track_pose as track_pose
from greybox.video._tracking import track_shuttle as track_shuttle
