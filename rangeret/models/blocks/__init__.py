"""The network's blocks, one per module, mapped to the thesis's figures: `stem` (REM),
`embedding` (VEM), `decay`, `position`, `token_mixing`, `kernels` and `retention` (multi-scale
retention), `ffn`, `backbone` (RetNet blocks) and `head` (Semantic Head)."""
