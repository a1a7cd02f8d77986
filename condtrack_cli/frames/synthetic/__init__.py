"""Synthetic image sequences with exact ground-truth point tracks.

Every scene is a stack of *layers*, bottom to top: layer 0 is a real photograph
(the background, moved by a known affine "camera" motion), the layers above are
textured objects (an occluder band, a disk) moved by their own known rigid maps.
Because each layer is a fixed image moved by an affine map, the position of any
point of layer ``l`` in frame ``k`` is exactly ``maps[l, k] @ (x0, y0, 1)``, with
``(x0, y0)`` its position in frame 0.

Pixel convention (every position here, as in the rest of the package): x to the
right, y down, in pixels, origin (0, 0) at the *centre* of the top-left pixel, so
pixel (row i, column j) has its centre at (x=j, y=i). This is OpenCV's convention.

Rendering of frame k, for a frame of W x H pixels:

1. every pixel centre is mapped back into the background photograph by the
   inverse of the layer's source -> frame k map and the photograph is sampled
   there by cubic B-spline interpolation (``scipy.ndimage.map_coordinates``,
   exact sub-pixel positions whatever the OpenCV version). The source region is
   chosen, magnified if need be, so that no frame ever sees past the photograph;
2. each object is sampled the same way from its texture and composited on top
   with an anti-aliased mask ``alpha = clip(sdf + 1/2, 0, 1)``, ``sdf`` the signed
   distance in pixels to the object's outline (positive inside);
3. global photometry ``128 + contrast * (I - 128) + bias``, then a Gaussian blur
   (only the ``illumination`` scene changes these), then Gaussian noise of standard
   deviation ``noise`` grey levels from ``np.random.default_rng``, then rounding
   and clipping to uint8.

A point is *visible* in frame k when it lies inside the frame (0 <= x <= W-1,
0 <= y <= H-1) and no layer above its own covers it (the upper layer's ``sdf`` is
<= 0 there). Positions are given on every frame, visible or not.

Query points are Shi-Tomasi corners (``cv2.goodFeaturesToTrack``) on a rendered
frame, restricted to the parts of each layer that are *clean*: at least
``BORDER_MARGIN`` pixels inside the frame and ``EDGE_MARGIN`` pixels away from
any layer outline, so that a query's patch never straddles an occluding edge.
Most are picked on frame 0; some scenes also pick background points that are
not visible on frame 0 (behind the occluder, or outside the frame), whose query
frame is then the first frame on which they are clean.

Files written by :func:`write_scene` (all positions with ``%.4f``, ``\\n`` line ends):

- ``00000.png``, ``00001.png``, ...: the frames, 8-bit grey PNG;
- ``queries.csv``: ``point_id,frame,x,y``, one row per point;
- ``tracks.csv``: ``point_id,frame,x,y,visible``, one row per point per frame,
  ordered by point then frame, ``visible`` 0/1;
- ``labels.csv``: ``point_id,layer``, the layer index of each point;
- ``scene.json``: scene name, seed, size, noise, layer names, the pixel
  convention and the per-layer maps ``maps[l][k]`` (2 x 3, frame 0 -> frame k).

Run ``condtrack synth DIR --samples`` to write the shipped samples, or
``condtrack synth DIR --scene NAME`` for one scene.

The exception is ``nonrigid`` (issue 45): its one layer is also deformed by smooth
time-varying displacement bumps (``deform``) on top of its affine map, which is all
``maps`` holds; its truth is the exact inverse of the renderer's backward map.

Modules: ``affine`` (maps), ``layers`` (shapes, textures, rendering), ``deform``
(non-rigid deformations), ``truth`` (positions, visibility, query picking), ``scenes``
(the eight scenes), ``files`` (writing).
"""

from condtrack_cli.frames.synthetic.files import write_samples, write_scene  # noqa: F401
from condtrack_cli.frames.synthetic.scenes import (  # noqa: F401
    DEFAULT_SIZE, SAMPLE_SEEDS, SCENES, Scene, make_scene,
)
from condtrack_cli.frames.synthetic.truth import BORDER_MARGIN  # noqa: F401
