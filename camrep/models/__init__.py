"""Flax Linen models of camrep: GQN-rooms encoder, decoders, shared layers (digest section 2) and
pose regressors (digest section 4)."""

from camrep.models.decoder import CarDecoder as CarDecoder
from camrep.models.decoder import CarDecoderTiny as CarDecoderTiny
from camrep.models.decoder import CarSceneTable as CarSceneTable
from camrep.models.decoder import GibsonDecoder as GibsonDecoder
from camrep.models.decoder import GibsonDecoderTiny as GibsonDecoderTiny
from camrep.models.decoder import GibsonSceneTable as GibsonSceneTable
from camrep.models.decoder import GQNDecoder as GQNDecoder
from camrep.models.decoder import GQNDecoderTiny as GQNDecoderTiny
from camrep.models.decoder import ResAdaINDecoder as ResAdaINDecoder
from camrep.models.decoder import SevenScenesDecoder as SevenScenesDecoder
from camrep.models.decoder import SevenScenesSceneTable as SevenScenesSceneTable
from camrep.models.decoder import UpConvDecoder as UpConvDecoder
from camrep.models.encoder import GQN_GENERATOR_HEADS as GQN_GENERATOR_HEADS
from camrep.models.encoder import GQNEncoder as GQNEncoder
from camrep.models.encoder import GQNEncoderTiny as GQNEncoderTiny
from camrep.models.encoder import Head as Head
from camrep.models.encoder import SceneEncoder as SceneEncoder
from camrep.models.layers import SceneTable as SceneTable
from camrep.models.layers import adain as adain
from camrep.models.layers import instance_norm as instance_norm
from camrep.models.layers import intermediate_shapes as intermediate_shapes
from camrep.models.layers import lrelu as lrelu
from camrep.models.layers import param_count as param_count
from camrep.models.layers import upsample2 as upsample2
from camrep.models.pose_regressor import GQN_REGRESSION_HEADS as GQN_REGRESSION_HEADS
from camrep.models.pose_regressor import CarRegressor as CarRegressor
from camrep.models.pose_regressor import GibsonRegressor as GibsonRegressor
from camrep.models.pose_regressor import GQNRegressor as GQNRegressor
from camrep.models.pose_regressor import PoseHeads as PoseHeads
from camrep.models.pose_regressor import ResNet34Regressor as ResNet34Regressor
from camrep.models.pose_regressor import ResNetRegressor as ResNetRegressor
from camrep.models.pose_regressor import ResNetRegressorTiny as ResNetRegressorTiny
from camrep.models.pose_regressor import load_torchvision_resnet34 as load_torchvision_resnet34
