"""Data and scoring: dataset readers in their official layouts
(:mod:`.datasets`), error metrics (:mod:`.metrics`), the OpenCV SGBM baseline
(:mod:`.baseline`) and the dataset evaluation behind ``mccnn-cl evaluate``
(:mod:`.scoring`)."""
