"""The dataset clip benchmark (its files: ``schemas/clips.py``): ``dataset`` exports clips from the public datasets
and scores generated frames (Tables I-III), ``generation`` makes frames for them with the configured synthesizer,
``reconstruction`` fits 3DGS per clip (Table IV)."""

from navcrafter.tasks.clips.dataset import clip_keys, export_clips, load_clip, load_generated, score_clip

__all__ = ["clip_keys", "export_clips", "load_clip", "load_generated", "score_clip"]
