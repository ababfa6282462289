"""Camera frames from files: sniffing, header probes, still decoding and video frames by time.

Torch-free (numpy, Pillow, PyAV). Every failure on untrusted bytes is a MediaError naming the
file; see decode.py (stills), video.py (videos), pixels.py (the resize and unit rules).
"""
from hope_models.media.decode import decode_image_bytes, decode_still, probe
from hope_models.media.errors import DEFAULT_MAX_PIXELS, MediaError
from hope_models.media.info import FrameInfo
from hope_models.media.pixels import area_resize, floats_to_uint8
from hope_models.media.sniff import sniff
from hope_models.media.video import VideoFrames

__all__ = ["DEFAULT_MAX_PIXELS", "FrameInfo", "MediaError", "VideoFrames", "area_resize", "decode_image_bytes", "decode_still",
           "floats_to_uint8", "probe", "sniff"]
