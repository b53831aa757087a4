"""Running a trade study's trials: on Dask (:mod:`.cluster`, :mod:`.runner`), cached by what
decides their figures (:mod:`.cache`), searched with Optuna's NSGA-II (:mod:`.search`). What a
trial measures is :mod:`hapticloud.core.studies.trade`'s."""
