"""Frame sources: folders of images and videos, streamed one frame at a time."""
