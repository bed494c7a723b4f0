"""The maths: SAC's update, its losses, the policy, the networks, DrQ's encoder, the learner that holds the state."""
