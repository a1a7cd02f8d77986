from condtrack_cli.frames.synthetic.scenes import (  # noqa: F401
    BORDER_MARGIN, DEFAULT_SIZE, SAMPLE_SEEDS, SCENES, Scene, make_scene, write_samples, write_scene,
)
