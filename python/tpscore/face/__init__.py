"""The vocabulary of a face: scan files, the face grid, landmarks, the frames faces are
compared in, regions, colour images and the reference face. Every method of tpscore
(expression transfer, template adaptation, the elastic model) speaks it."""
