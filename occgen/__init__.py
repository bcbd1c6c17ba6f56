"""occgen: 4D semantic occupancy generation (UniScene v2, Section "4D Occupancy Generation"), CPU-scaled.

Occupancy VAE (`vae`), latent DiT with BEV-layout condition (`dit`, `layout`), DDPM/DDIM (`diffusion`),
spatial expansion by 3D latent outpainting (`outpaint`), temporal forecasting with roll-out (`forecast`).
Grids are indexed [x, y, z] in the ego frame of `nuplan_occ.grid`; label ids from `nuplan_occ.labels`.
"""
