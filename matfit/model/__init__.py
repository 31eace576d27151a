"""The networks and what they learn from: the layers (`layers`), the decoder and the nine encoders with their
architecture records (`architectures`), one network's weights file (`weight_files`), a model directory in use
(`models`); the rendered training sets (`dataset` reads them, `dataset_writing` creates and fills them,
`dataset_workers` renders their chunks in local processes, `cluster` as Ray tasks), the input pipeline (`pipeline`),
training (`train`, with its settings `train_config`, its `losses` and its `checkpoints`) and evaluation with the model
card (`evaluate`). It may import `render` (training sets and references are renders of the test scene) and the shared
base, never `fit` or `app`."""
