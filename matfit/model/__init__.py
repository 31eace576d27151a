"""The networks and what they learn from: the decoder and the nine encoders with their weights (`models`), the rendered
training sets (`dataset`, rendered by a local process pool or as Ray tasks by `cluster`), the input pipeline
(`pipeline`), training (`train`) and evaluation with the model card (`evaluate`). It may import `render` (training
sets and references are renders of the test scene) and the shared base, never `fit` or `app`."""
