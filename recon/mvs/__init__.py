"""Classical multi-view stereo: plane-sweep depth maps, their cross-view check, fusion."""
