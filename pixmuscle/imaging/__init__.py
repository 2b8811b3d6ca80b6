"""Medical-image input: NIfTI volumes in cm and RAS+, DTI tensors and fibre features, resampling."""
