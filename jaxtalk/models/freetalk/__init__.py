"""FreeTalk: emotion-conditioned landmark diffusion (ATS) and DiffusionNet Sparse-To-Mesh (STM).

Modules: ``config`` (ATS / STM presets), ``emotions`` (labels, intensity checks), ``loss`` (the
unified motion loss), ``ats`` (denoiser, DDPM loss, DDIM sampling), ``stm`` (mesh encoder, landmark
GCN, cross-attention, DiffusionNet decoder), ``data`` (SynthTalk windows and audio features).
Import the submodules directly; this package only names them so that importing it stays cheap.
"""
