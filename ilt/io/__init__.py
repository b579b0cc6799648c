"""Files on disk, below every stage: what ilt reads and writes, and how it writes it.

``exr`` (float EXR and PNG through OpenImageIO), ``raw`` (RAW/DNG decoding through
rawpy: the green channel), ``exposure`` (EXIF exposure facts), ``frames`` (a merged
directory's beam frames and their pixel mapping), ``preview`` (log-scaled PNG figures),
``beams`` (capture beam directories and their manifests), ``manifest`` (stage manifests
and content fingerprints), ``atomic`` (temporary-then-rename writes), ``staged``
(stage directories written whole or not at all, and what they may replace), ``stage``
(run records: is a stage up to date), ``workspace_dirs`` (a workspace's directories).
"""

from ilt import lazy_face

__getattr__, __dir__, __all__ = lazy_face(
    __name__,
    {
        "atomic": ["atomic_path", "remove_stale_temporaries"],
        "beams": ["BEAM_GLOB", "FrameRecord", "beam_name", "write_beam_manifest"],
        "exposure": [
            "ExposureError", "ExposureFacts", "exif_facts", "parse_times", "read_exif",
            "resolve_facts",
        ],
        "exr": ["ImageError", "read_exr", "write_exr", "write_png"],
        "frames": [
            "FULL_RESOLUTION", "FrameError", "FrameScratch", "HDRDirectory", "PixelMapping",
            "load_frame", "open_hdr_directory", "read_frame",
        ],
        "manifest": [
            "LOG_NAME", "MANIFEST", "StageError", "fingerprint_array", "fingerprint_file",
            "read_manifest", "save_npy", "write_json", "write_manifest",
        ],
        "preview": ["bounce_panel", "log_scale", "matrix_panel", "save_png"],
        "raw": ["GreenInfo", "RawError", "read_color", "read_green", "to_full_frame"],
        "stage": ["DONE", "MISSING", "STALE", "StageState", "changed_outputs", "run_stage", "stage_state"],
        "staged": ["staged_directory"],
        "workspace_dirs": ["STAGE_DIRS", "Workspace", "workspace_marks"],
    },
)
