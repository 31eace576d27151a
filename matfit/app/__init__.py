"""What a user runs: the command line (`cli`, with its shared `options`, the `console` conventions and `progress`
bars), the edit-and-see page (`serve/`), the benchmarks (`bench/`, one module each) and the generator of the shipped
example edits (`examples`). It may import every other part; nothing imports it but `matfit.__main__`."""
