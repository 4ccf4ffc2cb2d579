"""Rewards: the universal rewards (collision, boundary, accessibility, floor contact, wall alignment,
object-count, class-presence, class-frequency and object-size priors, required classes) and the composite reward that sums
them with weights.
``iarcs_env`` never imports this package."""

from .composite import CompositeReward
from .universal import (REWARDS, accessibility_reward, boundary_reward, class_frequency_reward, class_presence_reward,
                        collision_reward, floor_contact_reward, get_reward, object_count_reward, object_size_reward,
                        register_reward, required_class_reward, wall_alignment_reward)

__all__ = ["REWARDS", "CompositeReward", "accessibility_reward", "boundary_reward", "class_frequency_reward",
           "class_presence_reward", "collision_reward", "floor_contact_reward", "get_reward", "object_count_reward",
           "object_size_reward", "register_reward", "required_class_reward", "wall_alignment_reward"]
