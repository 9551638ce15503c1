"""NR-MLS exported as standard skinning: training poses, fitted LBS weights, the fitted file."""
