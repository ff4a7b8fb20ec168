"""Clean image sources for training and evaluation (see ``docs/data.md``).

Every source gives gray float32 images ``1×H×W`` in [0, 1] (DN/255 for 8-bit, DN/65535 for 16-bit data;
colour → gray by ITU-R BT.601 luma) and has the same interface: ``len(source)``,
``source[i] -> (image, id: str)`` and ``source.ids``. Everything works offline: the default source uses
only the photographs bundled with scikit-image and the street frames committed in this package.
"""

from camhealth.data.dead_leaves import DeadLeavesSource, dead_leaves, dead_leaves_radius_pdf
from camhealth.data.image_folder import ImageFolderSource, list_images, natural_sort_key
from camhealth.data.io import BT601_WEIGHTS, IMAGE_EXTENSIONS, read_image, to_gray
from camhealth.data.skimage_photos import SKIMAGE_PHOTOS, SkimagePhotosSource, load_skimage_photo
from camhealth.data.sources import SPLITS, AreaDownsampledSource, ConcatSource, DefaultSource, build_source, group_key, split_ids
from camhealth.data.street_sample import (
    STREET_CLIP,
    STREET_DIR,
    StreetSampleSource,
    extract_street_frames,
    street_frame_paths,
    street_sequence,
)
from camhealth.data.video import VIDEO_EXTENSIONS, FrameSequence, FrameSequenceSource

__all__ = [
    "BT601_WEIGHTS",
    "IMAGE_EXTENSIONS",
    "VIDEO_EXTENSIONS",
    "to_gray",
    "read_image",
    "natural_sort_key",
    "list_images",
    "ImageFolderSource",
    "FrameSequence",
    "FrameSequenceSource",
    "dead_leaves",
    "dead_leaves_radius_pdf",
    "DeadLeavesSource",
    "SKIMAGE_PHOTOS",
    "load_skimage_photo",
    "SkimagePhotosSource",
    "STREET_DIR",
    "STREET_CLIP",
    "street_frame_paths",
    "StreetSampleSource",
    "street_sequence",
    "extract_street_frames",
    "AreaDownsampledSource",
    "ConcatSource",
    "DefaultSource",
    "build_source",
    "group_key",
    "split_ids",
    "SPLITS",
]
