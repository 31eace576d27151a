from matfit.model import pipeline


def test_the_loader_measure_gathers_batches_of_both_networks_arrays():
    figures = pipeline.measure_loader(8, 16, host_cast=True, samples=64, seconds=0.01)
    assert (figures["resolution"], figures["batch_size"]) == (8, 16)
    assert figures["decoder_samples_per_s"] > 0 and figures["encoder_samples_per_s"] > 0
    assert set(figures) == {"resolution", "batch_size", "decoder_samples_per_s", "encoder_samples_per_s"}
