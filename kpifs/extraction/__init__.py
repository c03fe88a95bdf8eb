"""From images to kernel phases: centring, windowing, Fourier phases at the model's uv
points, JWST filters as channels.
"""
