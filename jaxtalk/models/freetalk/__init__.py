"""FreeTalk: emotion-conditioned landmark diffusion (ATS) and DiffusionNet Sparse-To-Mesh (STM).

Modules: ``config`` (ATS / STM presets), ``emotions`` (labels, intensity checks), ``loss`` (the
unified motion loss, equation 15), ``ats`` (denoiser, DDPM loss, DDIM sampling), ``stm`` (mesh
encoder, landmark GCN, cross-attention, DiffusionNet decoder), ``data`` (SynthTalk audio features,
landmark/vertex displacement windows, remeshed faces), ``fit`` (training both modules with the shared
loop). Import the submodules directly; this package only names them so that importing it stays cheap.
"""
