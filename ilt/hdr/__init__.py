"""RAW brackets to linear HDR: decoding (raw), exposure facts (exposure), capture layout
(bracket), Mitsunaga-Nayar radiometric calibration (mitsunaga_nayar) and merging (merge)."""
