"""The safety-stop controller: never let the car hit what the lidar sees."""
