"""Users' own point clouds: npy/npz/bin/PCD/PLY files, poses and sweep directories (`point_files`, `pcd_ply`), and
sequences of them with timestamps and tracked boxes (`sequences`, `box_table`)."""
