"""The speed/accuracy trade study behind ``hapticloud study``: the knobs (:mod:`.knobs`), one
trial's measurement (:mod:`.evaluate`), the front and the presets (:mod:`.front`). Running the
trials (Dask, Optuna, the cache) is :mod:`hapticloud.hardware.study`'s."""
