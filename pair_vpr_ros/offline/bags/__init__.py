"""Reading recorded data: rosbags and image folders to frames, poses, depth and camera_info."""
