"""What timings are taken on: the machine (`machine`, named in every timing table) and the frames a user points a
camera at (`realistic`: a board drawn into clutter at a chosen size, frames without a board, real videos), used by
benchmarks/ and by the evaluations that score detectors on such frames."""
