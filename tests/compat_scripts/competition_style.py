"""A script written the way tmrl 0.7's competition template is: the memory is built from
``cfg_obj.MEM`` with the original's keywords (``imgs_obs``, ``dataset_path``,
``sample_preprocessor``), the environment, compressor and preprocessor come from
``config_objects``, and the trainer is given none of them. Used by tests/test_compat.py on a
simulator config: ``--server``, ``--trainer`` and ``--worker`` as three processes."""

import time
from argparse import ArgumentParser

import tmrl.config.config_constants as cfg
import tmrl.config.config_objects as cfg_obj
from tmrl.custom.custom_algorithms import SpinupSacAgent
from tmrl.networking import RolloutWorker, Server, Trainer
from tmrl.training_offline import TrainingOffline
from tmrl.util import partial

memory_cls = partial(cfg_obj.MEM, memory_size=cfg.TMRL_CONFIG["MEMORY_SIZE"], batch_size=cfg.TMRL_CONFIG["BATCH_SIZE"],
                     sample_preprocessor=None, dataset_path=cfg.DATASET_PATH, imgs_obs=cfg.IMG_HIST_LEN,
                     act_buf_len=cfg.ACT_BUF_LEN, crc_debug=False)
training_cls = partial(TrainingOffline, env_cls=cfg_obj.ENV_CLS, memory_cls=memory_cls,
                       training_agent_cls=partial(SpinupSacAgent, model_cls=cfg_obj.TRAIN_MODEL),
                       epochs=1, rounds=2, steps=10, update_buffer_interval=1, update_model_interval=5,
                       max_training_steps_per_env_step=1.0, start_training=200, device="cpu")

if __name__ == "__main__":
    parser = ArgumentParser()
    parser.add_argument("--server", action="store_true")
    parser.add_argument("--trainer", action="store_true")
    parser.add_argument("--worker", action="store_true")
    args = parser.parse_args()
    if args.trainer:
        Trainer(training_cls=training_cls, server_ip=cfg.SERVER_IP_FOR_TRAINER, server_port=cfg.PORT,
                password=cfg.PASSWORD, security=cfg.SECURITY).run()
    elif args.worker:
        rw = RolloutWorker(env_cls=cfg_obj.ENV_CLS, actor_module_cls=cfg_obj.POLICY,
                           sample_compressor=cfg_obj.SAMPLE_COMPRESSOR, device="cpu",
                           server_ip=cfg.SERVER_IP_FOR_WORKER, server_port=cfg.PORT, password=cfg.PASSWORD,
                           security=cfg.SECURITY, max_samples_per_episode=cfg.RW_MAX_SAMPLES_PER_EPISODE,
                           obs_preprocessor=cfg_obj.OBS_PREPROCESSOR)
        rw.run(test_episode_interval=10)
    elif args.server:
        serv = Server(port=cfg.PORT, password=cfg.PASSWORD, security=cfg.SECURITY)
        while True:
            time.sleep(1.0)
