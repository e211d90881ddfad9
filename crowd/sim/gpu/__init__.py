"""The crowd AI on the GPU: its state in storage buffers and its step as compute passes (GL 4.3), the
GPU twin of the numpy AI beside it (crowd.sim), which stays its float64 reference and the path of
contexts without compute."""
