"""A tutorial script written the way tmrl 0.7's minimal Pendulum tutorial is (same imports, same
calls, smaller numbers): server, worker thread and trainer in one process, nothing about logging.
Used by tests/test_compat.py: it must run unchanged and print its training progress."""

import sys
from threading import Thread

import tmrl.config.config_constants as cfg
from tmrl.custom.custom_algorithms import SpinupSacAgent
from tmrl.custom.custom_memories import GenericTorchMemory
from tmrl.custom.custom_models import MLPActorCritic, SquashedGaussianMLPActor
from tmrl.envs import GenericGymEnv
from tmrl.networking import RolloutWorker, Server, Trainer
from tmrl.training_offline import TorchTrainingOffline
from tmrl.util import partial

server_port = int(sys.argv[1])
env_cls = partial(GenericGymEnv, id="Pendulum-v1", gym_kwargs={"render_mode": None})
dummy_env = env_cls()
obs_space, act_space = dummy_env.observation_space, dummy_env.action_space

if __name__ == "__main__":
    my_server = Server(security=None, password=cfg.PASSWORD, port=server_port)
    my_worker = RolloutWorker(env_cls=env_cls, actor_module_cls=partial(SquashedGaussianMLPActor),
                              sample_compressor=None, device="cpu", server_ip="127.0.0.1", server_port=server_port,
                              password=cfg.PASSWORD, max_samples_per_episode=200,
                              model_path=str(cfg.WEIGHTS_FOLDER / "compat_pendulum.tmod"), model_history=-1)
    training_cls = partial(
        TorchTrainingOffline,
        env_cls=(obs_space, act_space),
        memory_cls=partial(GenericTorchMemory, memory_size=1e6, batch_size=32),
        training_agent_cls=partial(SpinupSacAgent, model_cls=MLPActorCritic, gamma=0.99, polyak=0.995, alpha=0.2,
                                   lr_actor=1e-3, lr_critic=1e-3, lr_entropy=1e-3, learn_entropy_coef=True,
                                   target_entropy=None),
        epochs=1, rounds=2, steps=20, update_buffer_interval=1, update_model_interval=1,
        max_training_steps_per_env_step=0.2, start_training=100, device=None)
    my_trainer = Trainer(training_cls=training_cls, server_ip="127.0.0.1", server_port=server_port,
                         password=cfg.PASSWORD, model_path=str(cfg.WEIGHTS_FOLDER / "compat_pendulum_t.tmod"),
                         checkpoint_path=None)
    Thread(target=my_worker.run, kwargs={"test_episode_interval": 10}, daemon=True).start()
    my_trainer.run()
    my_server.stop()
