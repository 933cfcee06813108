"""The application layer over the method (core), the codecs and the nodes: the
`skel-extract` command line (cli), the files it writes (outputs, bvh_export,
visualization), `replay` over the nodes, `record` (an example consumer), the scores
against ground truth (evaluation) and progress reporting."""
