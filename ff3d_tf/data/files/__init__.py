"""Users' own point clouds: npy/npz/bin/PCD/PLY files, poses and sweep directories."""
