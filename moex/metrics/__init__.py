"""Pure measurements on arrays or step maps (paper Sec. 3-4): errors, Lyapunov exponents,
symbol blocks and their KL divergence, switching statistics."""
