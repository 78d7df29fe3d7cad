"""The recording's topic names (one definition; the converters write them, the estimators read them)."""

TOPIC_IMU = "/imu"
TOPIC_CAM0 = "/cam0/image_raw"
TOPIC_CAM1 = "/cam1/image_raw"
TOPIC_FEATURES = "/cam0/features"
TOPIC_RANGE = "/uwb/range"
TOPIC_GT_POSE = "/groundtruth/pose"
TOPIC_GT_POSITION = "/groundtruth/position"
# ground-truth IMU biases (EuRoC state_groundtruth_estimate0 b_w, b_a) as sensor_msgs/Imu:
# angular_velocity = gyro bias [rad/s], linear_acceleration = accelerometer bias [m/s^2]
TOPIC_GT_IMU_BIAS = "/groundtruth/imu_bias"
TOPIC_ODOM = "/odometry"
TOPIC_VIO = "/vio/odometry"
