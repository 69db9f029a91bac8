"""The network's blocks, one per module, mapped to the thesis's figures: `stem` (REM),
`embedding` (VEM), `decay`, `position`, `token_mixing`, `kernels` and `retention` (multi-scale
retention), `ffn`, `backbone` (RetNet blocks) and `head` (Semantic Head). `inference_stem` and
`inference_forms` hold the blocks' inference forms, which `rangeret.inference.runtime.fast_graph`
assembles."""
